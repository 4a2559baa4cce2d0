// The training step's kernels (nimbus/kernels/train_step.py): the loss with its gradient, and
// the finiteness check of the gradients (alone, or with GGS's per-row scaling), each in one pass.
//
// The loss (1 - lambda) L1 + lambda (1 - mean SSIM) of one [H, W, C] image pair
// (optionally masked) and its gradient w.r.t. the prediction are one op.
//
// The SSIM is the 3dgs protocol of nimbus/metrics/image.py (Gaussian window, zero 'same'
// padding, mean over the map); the 2-D window is the outer product of its taps, so every
// filter here is separable: a horizontal then a vertical pass of taps.size() taps, with
// the pixel rows as the unit of parallel work.  The torch path runs five 11x11
// depthwise convolutions forward and their transposes backward; here the forward
// filters the five moment images (x, y, x^2, y^2, xy) and the same pass already forms
// the per-pixel derivatives of the SSIM map w.r.t. the three moments that depend on x
// (E[x], E[x^2], E[xy]); the gradient is their filtered maps combined per pixel:
//
//   d mean(S) / d x_p = (1/N) [ F(dS/dE[x])_p + 2 x_p F(dS/dE[x^2])_p + y_p F(dS/dE[xy])_p ]
//
// (F: the window filter; it is its own adjoint, being symmetric with zero padding).
// Sums run over taps in a fixed order and the loss's sums over rows in row order, so
// the result is bitwise the same for any thread count.  float32 filters in float32 (as
// the torch path's convolutions do), float64 in float64; the two means are accumulated
// in double.  Same value as the torch path up to rounding, not bit for bit.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/Exception.h>
#include <torch/library.h>

#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <tuple>
#include <vector>

namespace nimbus_train_step {
namespace {

// Rows per parallel task: a row is a few microseconds of work.
constexpr int64_t kRowGrain = 8;

// Filters every row of `planes` images [P][H][W] horizontally: out[p][y][x] = sum_k w[k] in[p][y][x + k - r].
template <typename S>
void filter_rows(const S* in, S* out, int64_t P, int64_t H, int64_t W, const std::vector<S>& w) {
  const int64_t K = static_cast<int64_t>(w.size()), r = K / 2;
  at::parallel_for(0, P * H, kRowGrain, [&](int64_t b, int64_t e) {
    std::vector<S> pad(W + 2 * r, S(0));
    for (int64_t row = b; row < e; ++row) {
      const S* src = in + row * W;
      S* dst = out + row * W;
      for (int64_t x = 0; x < W; ++x) pad[x + r] = src[x];
      for (int64_t x = 0; x < W; ++x) dst[x] = w[0] * pad[x];
      for (int64_t k = 1; k < K; ++k) {
        const S wk = w[k];
        const S* p = pad.data() + k;
        for (int64_t x = 0; x < W; ++x) dst[x] += wk * p[x];
      }
    }
  });
}

// Vertical pass of one row: dst[x] = sum_k w[k] src[y + k - r][x] over the rows inside the image.
template <typename S>
inline void filter_column(const S* plane, S* dst, int64_t y, int64_t H, int64_t W, const std::vector<S>& w) {
  const int64_t K = static_cast<int64_t>(w.size()), r = K / 2;
  for (int64_t x = 0; x < W; ++x) dst[x] = S(0);
  for (int64_t k = 0; k < K; ++k) {
    const int64_t yy = y + k - r;
    if (yy < 0 || yy >= H) continue;
    const S wk = w[k];
    const S* src = plane + yy * W;
    for (int64_t x = 0; x < W; ++x) dst[x] += wk * src[x];
  }
}

// The SSIM window's 1-D taps: an odd-length contiguous float64 vector.
void check_taps(const at::Tensor& taps) {
  TORCH_CHECK(taps.scalar_type() == at::kDouble && taps.dim() == 1 && taps.size(0) % 2 == 1 &&
                  taps.is_contiguous(),
              "taps must be an odd-length contiguous float64 [K] tensor");
}

// Whether a validity mask is given (non-empty); one that is must be a contiguous CPU [H, W] tensor of the
// images' dtype (`of` names the image in the message).
bool check_mask(const at::Tensor& mask, int64_t H, int64_t W, at::ScalarType dtype, const char* of) {
  const bool masked = mask.numel() > 0;
  TORCH_CHECK(!masked || (mask.sizes() == at::IntArrayRef({H, W}) && mask.scalar_type() == dtype &&
                          mask.is_contiguous() && mask.device().is_cpu()),
              "mask must be empty or a contiguous CPU [H, W] tensor of ", of, "'s dtype");
  return masked;
}

// The filtered moments of the target alone, F(y) and F(y^2), [2][C][H][W] in gt's dtype (y masked as in
// photometric_loss): the same filters and order photometric_loss applies to them, so passing them back
// as `gt_moments` gives the same bits while it filters only the three moments that depend on pred.
at::Tensor target_moments(const at::Tensor& gt, const at::Tensor& mask, const at::Tensor& taps) {
  TORCH_CHECK(gt.dim() == 3 && gt.device().is_cpu() && gt.is_contiguous() &&
                  (gt.scalar_type() == at::kFloat || gt.scalar_type() == at::kDouble),
              "target_moments: gt must be a contiguous CPU float [H, W, C] tensor");
  check_taps(taps);
  const int64_t H = gt.size(0), W = gt.size(1), C = gt.size(2), HW = H * W;
  TORCH_CHECK(H > 0 && W > 0 && C > 0, "target_moments: empty image");
  const bool masked = check_mask(mask, H, W, gt.scalar_type(), "gt");
  at::Tensor out = at::empty({2, C, H, W}, gt.options());
  AT_DISPATCH_FLOATING_TYPES(gt.scalar_type(), "target_moments", [&] {
    using S = scalar_t;
    const S* yp = gt.data_ptr<S>();
    const S* mp = masked ? mask.data_ptr<S>() : nullptr;
    const double* tp = taps.data_ptr<double>();
    const std::vector<S> w(tp, tp + taps.size(0));
    std::unique_ptr<S[]> mom(new S[2 * C * HW]), hmom(new S[2 * C * HW]);
    at::parallel_for(0, C * H, kRowGrain, [&](int64_t b, int64_t e) {
      for (int64_t row = b; row < e; ++row) {
        const int64_t c = row / H, y = row % H;
        for (int64_t x = 0; x < W; ++x) {
          S g = yp[(y * W + x) * C + c];
          if (masked) g *= mp[y * W + x];
          const int64_t i = c * HW + y * W + x;
          mom[i] = g;
          mom[C * HW + i] = g * g;
        }
      }
    });
    filter_rows(mom.get(), hmom.get(), 2 * C, H, W, w);
    S* o = out.data_ptr<S>();
    at::parallel_for(0, C * H, kRowGrain, [&](int64_t b, int64_t e) {
      for (int64_t row = b; row < e; ++row) {
        const int64_t c = row / H, y = row % H;
        for (int q = 0; q < 2; ++q)
          filter_column(hmom.get() + (q * C + c) * HW, o + (q * C + c) * HW + y * W, y, H, W, w);
      }
    });
  });
  return out;
}

// Returns the loss (0-d) and, when need_grad, its gradient w.r.t. pred [H, W, C] (else an empty tensor).
// mask: [H, W] of 0 / 1 in pred's dtype, or empty for none: as nimbus.metrics.masked_pair, both
// images are multiplied by it and both means run over the valid pixels only.  gt_moments: empty, or
// target_moments(gt, mask, taps) of this gt, mask and taps (the caller's promise; the result is then
// the same, bit for bit, with two of the five filtered moments read instead of computed).
std::tuple<at::Tensor, at::Tensor> photometric_loss(const at::Tensor& pred, const at::Tensor& gt,
                                                    const at::Tensor& mask, const at::Tensor& taps,
                                                    double lambda_dssim, double c1, double c2, bool need_grad,
                                                    const at::Tensor& gt_moments) {
  TORCH_CHECK(pred.dim() == 3 && pred.sizes() == gt.sizes(), "pred and gt must be [H, W, C] of one shape");
  TORCH_CHECK(pred.scalar_type() == gt.scalar_type(), "pred and gt must share one dtype");
  TORCH_CHECK(pred.device().is_cpu() && gt.device().is_cpu(), "photometric_loss: CPU tensors only");
  TORCH_CHECK(pred.is_contiguous() && gt.is_contiguous(), "photometric_loss: inputs must be contiguous");
  check_taps(taps);
  const int64_t H = pred.size(0), W = pred.size(1), C = pred.size(2), HW = H * W;
  TORCH_CHECK(H > 0 && W > 0 && C > 0, "photometric_loss: empty image");
  const bool masked = check_mask(mask, H, W, pred.scalar_type(), "pred");
  const bool cached = gt_moments.numel() > 0;
  TORCH_CHECK(!cached || (gt_moments.sizes() == at::IntArrayRef({2, C, H, W}) &&
                          gt_moments.scalar_type() == pred.scalar_type() && gt_moments.is_contiguous() &&
                          gt_moments.device().is_cpu()),
              "gt_moments must be empty or target_moments(gt, mask, taps): a contiguous CPU [2, C, H, W] tensor");
  at::Tensor loss = at::empty({}, pred.options());
  at::Tensor grad = need_grad ? at::empty({H, W, C}, pred.options()) : at::empty({0}, pred.options());
  AT_DISPATCH_FLOATING_TYPES(pred.scalar_type(), "photometric_loss", [&] {
    using S = scalar_t;
    const S* xp = pred.data_ptr<S>();
    const S* yp = gt.data_ptr<S>();
    const S* mp = masked ? mask.data_ptr<S>() : nullptr;
    const double* tp = taps.data_ptr<double>();
    const std::vector<S> w(tp, tp + taps.size(0));
    const S C1 = static_cast<S>(c1), C2 = static_cast<S>(c2);
    // Planar moments [5][C][H][W]: x, x^2, xy (those that depend on pred), then y, y^2; the L1 sum per
    // row (C * H rows).  Every element of both buffers that is read is written first: left
    // uninitialised.  With gt_moments the last two planes are neither formed nor filtered.
    const int planes = cached ? 3 : 5;
    std::unique_ptr<S[]> mom(new S[planes * C * HW]), hmom(new S[planes * C * HW]);
    const S* gm = cached ? gt_moments.data_ptr<S>() : nullptr;
    std::vector<double> row_l1(C * H, 0.0), row_ssim(C * H, 0.0);
    at::parallel_for(0, C * H, kRowGrain, [&](int64_t b, int64_t e) {
      for (int64_t row = b; row < e; ++row) {
        const int64_t c = row / H, y = row % H;
        double l1 = 0.0;
        for (int64_t x = 0; x < W; ++x) {
          S a = xp[(y * W + x) * C + c], g = yp[(y * W + x) * C + c];
          if (masked) {
            a *= mp[y * W + x];
            g *= mp[y * W + x];
          }
          const int64_t i = c * HW + y * W + x;
          mom[i] = a;
          mom[C * HW + i] = a * a;
          mom[2 * C * HW + i] = a * g;
          if (!cached) {
            mom[3 * C * HW + i] = g;
            mom[4 * C * HW + i] = g * g;
          }
          l1 += std::abs(static_cast<double>(a) - static_cast<double>(g));
        }
        row_l1[row] = l1;
      }
    });
    filter_rows(mom.get(), hmom.get(), planes * C, H, W, w);
    // The moments' filtered values are no longer needed once the map and its derivatives
    // are formed: `mom` is reused for dS/dE[x], dS/dE[x^2], dS/dE[xy] (planes 0..2).
    S* dmap = mom.get();
    at::parallel_for(0, C * H, kRowGrain, [&](int64_t b, int64_t e) {
      std::vector<S> f(5 * W);
      for (int64_t row = b; row < e; ++row) {
        const int64_t c = row / H, y = row % H;
        for (int q = 0; q < planes; ++q)
          filter_column(hmom.get() + (q * C + c) * HW, f.data() + q * W, y, H, W, w);
        const S* fy = cached ? gm + c * HW + y * W : f.data() + 3 * W;  // F(y); F(y^2) follows one plane on
        const int64_t fyy = cached ? C * HW : W;
        double sum = 0.0;
        for (int64_t x = 0; x < W; ++x) {
          const S mx = f[x], my = fy[x];
          const S sxx = f[W + x] - mx * mx, syy = fy[fyy + x] - my * my, sxy = f[2 * W + x] - mx * my;
          const S A = S(2) * mx * my + C1, B = S(2) * sxy + C2;
          const S Cm = mx * mx + my * my + C1, D = sxx + syy + C2;
          const S den = Cm * D;
          const S s = (A * B) / den;
          const S wq = masked ? mp[y * W + x] : S(1);  // the pixel's weight in the mean
          sum += static_cast<double>(masked ? s * wq : s);
          if (need_grad) {
            const S d_mx = wq * (S(2) * my * B / den - s * S(2) * mx / Cm);  // sigma's held fixed
            const S d_sxy = wq * (S(2) * A / den);
            const S d_sxx = wq * (-s / D);
            const int64_t i = c * HW + y * W + x;
            dmap[i] = d_mx - S(2) * mx * d_sxx - my * d_sxy;  // E[x] enters mu_x, sxx and sxy
            dmap[C * HW + i] = d_sxx;
            dmap[2 * C * HW + i] = d_sxy;
          }
        }
        row_ssim[row] = sum;
      }
    });
    double l1 = 0.0, ssim = 0.0;
    for (int64_t row = 0; row < C * H; ++row) {
      l1 += row_l1[row];
      ssim += row_ssim[row];
    }
    double valid = static_cast<double>(HW);
    if (masked) {
      valid = 0.0;
      for (int64_t i = 0; i < HW; ++i) valid += static_cast<double>(mp[i]);
    }
    const double n = static_cast<double>(C) * valid;
    *loss.data_ptr<S>() = static_cast<S>((1.0 - lambda_dssim) * (l1 / n) + lambda_dssim * (1.0 - ssim / n));
    if (!need_grad) return;
    filter_rows(dmap, hmom.get(), 3 * C, H, W, w);
    S* gp = grad.data_ptr<S>();
    const S k_l1 = static_cast<S>((1.0 - lambda_dssim) / n), k_ssim = static_cast<S>(-lambda_dssim / n);
    at::parallel_for(0, C * H, kRowGrain, [&](int64_t b, int64_t e) {
      std::vector<S> f(3 * W);
      for (int64_t row = b; row < e; ++row) {
        const int64_t c = row / H, y = row % H;
        for (int q = 0; q < 3; ++q) filter_column(hmom.get() + (q * C + c) * HW, f.data() + q * W, y, H, W, w);
        for (int64_t x = 0; x < W; ++x) {
          const int64_t i = (y * W + x) * C + c;
          const S wp = masked ? mp[y * W + x] : S(1);
          const S a = xp[i] * wp, g = yp[i] * wp;
          const S ds = f[x] + S(2) * a * f[W + x] + g * f[2 * W + x];
          const S sign = a > g ? S(1) : (a < g ? S(-1) : S(0));  // torch's abs backward: 0 at a tie
          gp[i] = masked ? (k_l1 * sign + k_ssim * ds) * wp : k_l1 * sign + k_ssim * ds;
        }
      }
    });
  });
  return {loss, grad};
}

// --- the gradient guard ------------------------------------------------------------------
// Elements per task of all_finite.
constexpr int64_t kFiniteGrain = 1 << 15;

// Whether x is not finite, as an integer test on its bits (|x| at or above infinity's bit pattern: inf,
// NaN) that GCC vectorises with any SSE2, where std::isfinite kept these loops scalar (4.7 ms for the
// 47 MB of a 198k-Gaussian model's gradients, against 3.4 ms to scale them).
template <typename T>
struct FloatBits;
template <>
struct FloatBits<float> {
  using Int = int32_t;
  static constexpr Int kAbs = 0x7fffffff;
  static constexpr Int kInf = 0x7f800000;
};
template <>
struct FloatBits<double> {
  using Int = int64_t;
  static constexpr Int kAbs = 0x7fffffffffffffffLL;
  static constexpr Int kInf = 0x7ff0000000000000LL;
};
template <typename T>
inline typename FloatBits<T>::Int not_finite(T x) {
  typename FloatBits<T>::Int bits;
  std::memcpy(&bits, &x, sizeof(T));
  return (bits & FloatBits<T>::kAbs) >= FloatBits<T>::kInf;
}

// Whether every element of every tensor is finite (one read pass, no temporaries).
bool all_finite(const std::vector<at::Tensor>& tensors) {
  for (const at::Tensor& x : tensors) {
    TORCH_CHECK(x.is_contiguous() && x.device().is_cpu(), "all_finite: contiguous CPU tensors only");
    bool ok = true;
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "all_finite", [&] {
      const scalar_t* d = x.data_ptr<scalar_t>();
      std::atomic<bool> bad{false};
      at::parallel_for(0, x.numel(), kFiniteGrain, [&](int64_t b, int64_t e) {
        typename FloatBits<scalar_t>::Int any = 0;
        for (int64_t i = b; i < e; ++i) any |= not_finite(d[i]);
        if (any) bad.store(true, std::memory_order_relaxed);
      });
      ok = !bad.load();
    });
    if (!ok) return false;
  }
  return true;
}

// Rows per task of scale_rows_all_finite.
constexpr int64_t kScaleGrain = 1 << 10;

// Multiply row i of every tensor (first dimension N) by weights[i] in place, and say whether every
// product is finite: NimbusGS's GGS scaling and the gradient guard in one pass instead of a write
// pass and a read pass.  Each element is x * w[i] in the tensor's dtype, as torch's broadcast mul_.
bool scale_rows_all_finite(const std::vector<at::Tensor>& tensors, const at::Tensor& weights) {
  TORCH_CHECK(weights.dim() == 1 && weights.is_contiguous() && weights.device().is_cpu(),
              "scale_rows_all_finite: weights must be a contiguous CPU vector");
  const int64_t n = weights.size(0);
  bool ok = true;
  for (const at::Tensor& x : tensors) {
    TORCH_CHECK(x.is_contiguous() && x.device().is_cpu() && x.dim() >= 1 && x.size(0) == n &&
                    x.scalar_type() == weights.scalar_type(),
                "scale_rows_all_finite: contiguous CPU tensors of N rows and the weights' dtype only");
    if (x.numel() == 0) continue;
    const int64_t cols = x.numel() / n;
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "scale_rows_all_finite", [&] {
      scalar_t* d = x.data_ptr<scalar_t>();
      const scalar_t* w = weights.data_ptr<scalar_t>();
      std::atomic<bool> bad{false};
      at::parallel_for(0, n, kScaleGrain, [&](int64_t b, int64_t e) {
        typename FloatBits<scalar_t>::Int any = 0;
        for (int64_t i = b; i < e; ++i) {
          scalar_t* row = d + i * cols;
          const scalar_t wi = w[i];
          for (int64_t j = 0; j < cols; ++j) {
            const scalar_t v = row[j] * wi;
            row[j] = v;
            any |= not_finite(v);
          }
        }
        if (any) bad.store(true, std::memory_order_relaxed);
      });
      ok = ok && !bad.load();
    });
  }
  return ok;
}

}  // namespace
}  // namespace nimbus_train_step

TORCH_LIBRARY(nimbus_train_step, m) {
  m.def("photometric_loss", &nimbus_train_step::photometric_loss);
  m.def("target_moments", &nimbus_train_step::target_moments);
  m.def("all_finite", &nimbus_train_step::all_finite);
  m.def("scale_rows_all_finite", &nimbus_train_step::scale_rows_all_finite);
}
