// CPU forward and backward of NimbusGS's network airlight (nimbus/methods/nimbusgs/airlight.py), fused.
//
// The MLP, per row r of P (one row per pixel):
//
//   z1 = x W1^T + b1          x [P, I] (the detached features), W1 [H, I]
//   z2 = silu(z1) W2^T + b2   W2 [H, H]
//   A  = sigmoid(base + silu(z2) W3^T + b3)    W3 [O, H], base [O]
//
// with silu(z) = z sigmoid(z).  torch evaluates it as five ops over [P, H] tensors (two
// matrix products, two SiLUs, the last product) and as many again backward, each a pass
// through main memory; here a block of kRows rows goes through every layer while it is
// in cache, forward and backward.  The forward keeps z1 and z2 [P, H] for the backward
// (the inputs of the SiLUs), which recomputes their SiLUs.  Gradients go to the weights
// and biases only: x and base are constants (the Python wrapper uses the torch MLP when
// they need gradients).
//
// Arithmetic: every output element is its initial value (bias or 0) plus the products
// over the summed index in order, with no FMA contraction, so the AVX2 clone computes the
// generic code's numbers.  float32 takes sigmoid's exp from the Cephes polynomial of
// common.h (~1e-7 relative), float64 (gradcheck, tests) std::exp.  The weight gradients
// are summed per part (rows split by their number alone: kMaxParts, kMinRowsPerPart) and the
// parts' sums added in part order: the same bits for any thread count, as the march's.
//
// Registered as torch.ops.nimbus_airlight.*; built into NimbusGS's extension with
// march.cpp by nimbus/kernels/march.py.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <c10/util/Exception.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <tuple>
#include <vector>

#include "medium.h"

namespace nimbus_airlight {
namespace {

using namespace nimbus_simd;

// Rows per block: its activations ([kRows, H] each) stay in the core's cache through every layer.
constexpr int64_t kRows = 64;
// Rows per part below which another part does not pay for its gradient buffers.
constexpr int64_t kMinRowsPerPart = 2048;
// The backward's parts: min(kMaxParts, P / kMinRowsPerPart), fixed by P alone (threads share them out).
constexpr int64_t kMaxParts = 8;
// Register tiles of C: kWideRows rows by kWideVecs vectors (one broadcast of A feeds four
// multiplies), and for the columns left over kNarrowRows rows by one vector.
constexpr int kWideRows = 2;
constexpr int kWideVecs = 4;
constexpr int kNarrowRows = 4;

// C[m, n] += sum_k A[m * am + k * ak] * B[k * ldb + n] for MR rows and NV vectors of columns, k in order.
template <typename T, int MR, int NV>
NIMBUS_INLINE void tile(int64_t K, const T* A, int64_t am, int64_t ak, const T* B, int64_t ldb, T* C, int64_t ldc) {
  using V = Vec<T>;
  V acc[MR][NV];
  for (int m = 0; m < MR; ++m)
    for (int v = 0; v < NV; ++v) acc[m][v] = load<V>(C + m * ldc + v * kLanes);
  for (int64_t k = 0; k < K; ++k) {
    V b[NV];
    for (int v = 0; v < NV; ++v) b[v] = load<V>(B + k * ldb + v * kLanes);
    for (int m = 0; m < MR; ++m) {
      const V a = splat(A[m * am + k * ak]);
      for (int v = 0; v < NV; ++v) acc[m][v] = acc[m][v] + a * b[v];
    }
  }
  for (int m = 0; m < MR; ++m)
    for (int v = 0; v < NV; ++v) store(C + m * ldc + v * kLanes, acc[m][v]);
}

// The rows m0 .. M - 1 of columns [n0, n0 + NV * kLanes) in tiles of MR rows, then single rows.
template <typename T, int MR, int NV>
NIMBUS_INLINE void tile_rows(int64_t M, int64_t n0, int64_t K, const T* A, int64_t am, int64_t ak, const T* B,
                             int64_t ldb, T* C, int64_t ldc) {
  int64_t m = 0;
  for (; m + MR <= M; m += MR) tile<T, MR, NV>(K, A + m * am, am, ak, B + n0, ldb, C + m * ldc + n0, ldc);
  for (; m < M; ++m) tile<T, 1, NV>(K, A + m * am, am, ak, B + n0, ldb, C + m * ldc + n0, ldc);
}

// C [M, N] (row stride ldc) += A B with A(m, k) = A[m * am + k * ak] and B [K, N] (row stride ldb).
template <typename T>
NIMBUS_INLINE void gemm_acc(int64_t M, int64_t N, int64_t K, const T* A, int64_t am, int64_t ak, const T* B,
                            int64_t ldb, T* C, int64_t ldc) {
  constexpr int64_t wide = kWideVecs * kLanes;
  int64_t n = 0;
  for (; n + wide <= N; n += wide) tile_rows<T, kWideRows, kWideVecs>(M, n, K, A, am, ak, B, ldb, C, ldc);
  for (; n + kLanes <= N; n += kLanes) tile_rows<T, kNarrowRows, 1>(M, n, K, A, am, ak, B, ldb, C, ldc);
  for (int64_t m = 0; m < M && n < N; ++m) {  // the columns left of a whole vector, one at a time
    for (int64_t j = n; j < N; ++j) {
      T s = C[m * ldc + j];
      for (int64_t k = 0; k < K; ++k) s = s + A[m * am + k * ak] * B[k * ldb + j];
      C[m * ldc + j] = s;
    }
  }
}

// sigmoid(z) of n values (out may alias z).
NIMBUS_INLINE void sigmoid_block(const double* z, double* out, int64_t n) {
  for (int64_t j = 0; j < n; ++j) out[j] = 1.0 / (1.0 + std::exp(-z[j]));
}
NIMBUS_INLINE void sigmoid_block(const float* z, float* out, int64_t n) {
  using V = Vec<float>;
  int64_t j = 0;
  for (; j + kLanes <= n; j += kLanes) store(out + j, sigmoid(load<V>(z + j)));
  if (j < n) {  // a part vector goes through the same arithmetic as a whole one
    float buf[kLanes] = {};
    std::copy(z + j, z + n, buf);
    store(buf, sigmoid(load<V>(buf)));
    std::copy(buf, buf + (n - j), out + j);
  }
}

// h = silu(z) = z sigmoid(z) over n values; with s, sigmoid(z) is kept there too.
template <typename T>
NIMBUS_INLINE void silu_block(const T* z, T* h, int64_t n, T* s = nullptr) {
  T* sig = s ? s : h;
  sigmoid_block(z, sig, n);
  for (int64_t j = 0; j < n; ++j) h[j] = z[j] * sig[j];
}

// g *= silu'(z) = s (1 + z (1 - s)) with s = sigmoid(z) given (torch's silu_backward).
template <typename T>
NIMBUS_INLINE void silu_grad_block(const T* z, const T* s, T* g, int64_t n) {
  for (int64_t j = 0; j < n; ++j) g[j] = g[j] * (s[j] * (T(1) + z[j] * (T(1) - s[j])));
}

// Each row of C [rows, n] set to bias [n].
template <typename T>
NIMBUS_INLINE void fill_rows(T* C, const T* bias, int64_t rows, int64_t n) {
  for (int64_t r = 0; r < rows; ++r) std::copy(bias, bias + n, C + r * n);
}

// The weights, transposed where the products read them by rows.
template <typename T>
struct Net {
  int64_t I, H, O;
  const T *w1t, *b1, *w2, *w2t, *b2, *w3, *b3, *base;
};

// One block of rows forward: z1, z2 [rows, H] written, a [rows, O] the output; h1, h2 scratch [rows, H]
// and at [O, rows].  The last layer runs on silu(z2) transposed (in h1), so that its O outputs are
// computed a vector of rows at a time.
template <typename T>
NIMBUS_INLINE void forward_block(const Net<T>& n, const T* x, int64_t rows, T* z1, T* z2, T* h1, T* h2, T* at,
                                 T* a) {
  const int64_t I = n.I, H = n.H, O = n.O;
  fill_rows(z1, n.b1, rows, H);
  gemm_acc(rows, H, I, x, I, 1, n.w1t, H, z1, H);
  silu_block(z1, h1, rows * H);
  fill_rows(z2, n.b2, rows, H);
  gemm_acc(rows, H, H, h1, H, 1, n.w2t, H, z2, H);
  silu_block(z2, h2, rows * H);
  for (int64_t r = 0; r < rows; ++r)
    for (int64_t k = 0; k < H; ++k) h1[k * rows + r] = h2[r * H + k];
  for (int64_t c = 0; c < O; ++c) std::fill(at + c * rows, at + (c + 1) * rows, n.b3[c]);
  gemm_acc(O, rows, H, n.w3, H, 1, h1, rows, at, rows);
  for (int64_t r = 0; r < rows; ++r)
    for (int64_t c = 0; c < O; ++c) a[r * O + c] = n.base[c] + at[c * rows + r];
  sigmoid_block(a, a, rows * O);
}

template <typename T>
struct Grads {
  std::vector<T> w1t, b1, w2, b2, w3, b3;  // w1t [I, H]: transposed back at the end
  explicit Grads(const Net<T>& n)
      : w1t(n.I * n.H), b1(n.H), w2(n.H * n.H), b2(n.H), w3(n.O * n.H), b3(n.O) {}
  void add(const Grads& o) {
    auto sum = [](std::vector<T>& dst, const std::vector<T>& src) {
      for (size_t i = 0; i < dst.size(); ++i) dst[i] += src[i];
    };
    sum(w1t, o.w1t), sum(b1, o.b1), sum(w2, o.w2), sum(b2, o.b2), sum(w3, o.w3), sum(b3, o.b3);
  }
};

template <typename T>
NIMBUS_INLINE void add_column_sums(const T* g, int64_t rows, int64_t n, T* out) {
  for (int64_t r = 0; r < rows; ++r)
    for (int64_t j = 0; j < n; ++j) out[j] = out[j] + g[r * n + j];
}

// One block of rows backward, accumulating into acc.  Scratch: sc [5 * rows * H] (the SiLUs, their
// sigmoids, one gradient) and go [rows * O].
template <typename T>
NIMBUS_INLINE void backward_block(const Net<T>& n, const T* x, int64_t rows, const T* z1, const T* z2, const T* a,
                                  const T* ga, T* sc, T* go, Grads<T>& acc) {
  const int64_t I = n.I, H = n.H, O = n.O, size = rows * H;
  T *h1 = sc, *h2 = sc + size, *s1 = sc + 2 * size, *s2 = sc + 3 * size, *gh = sc + 4 * size;
  for (int64_t j = 0; j < rows * O; ++j) go[j] = ga[j] * (a[j] * (T(1) - a[j]));  // through the sigmoid
  silu_block(z1, h1, size, s1);
  silu_block(z2, h2, size, s2);
  add_column_sums(go, rows, O, acc.b3.data());
  gemm_acc(O, H, rows, go, 1, O, h2, H, acc.w3.data(), H);         // dW3 = go^T h2
  std::fill(gh, gh + size, T(0));
  gemm_acc(rows, H, O, go, O, 1, n.w3, H, gh, H);                  // d h2 = go W3
  silu_grad_block(z2, s2, gh, size);                               // d z2
  add_column_sums(gh, rows, H, acc.b2.data());
  gemm_acc(H, H, rows, gh, 1, H, h1, H, acc.w2.data(), H);         // dW2 = dz2^T h1
  std::fill(h2, h2 + size, T(0));                                  // h2 is done with: d h1 goes there
  gemm_acc(rows, H, H, gh, H, 1, n.w2, H, h2, H);                  // d h1 = dz2 W2
  silu_grad_block(z1, s1, h2, size);                               // d z1
  add_column_sums(h2, rows, H, acc.b1.data());
  gemm_acc(I, H, rows, x, 1, I, h2, H, acc.w1t.data(), H);         // dW1^T = x^T dz1
}

// The float32 block functions, generic and AVX2 (the same arithmetic; the clone is picked per call).
void forward_block_generic(const Net<float>& n, const float* x, int64_t rows, float* z1, float* z2, float* h1,
                           float* h2, float* at, float* a) {
  forward_block(n, x, rows, z1, z2, h1, h2, at, a);
}
void backward_block_generic(const Net<float>& n, const float* x, int64_t rows, const float* z1, const float* z2,
                            const float* a, const float* ga, float* sc, float* go, Grads<float>& acc) {
  backward_block(n, x, rows, z1, z2, a, ga, sc, go, acc);
}
#ifdef NIMBUS_HAS_AVX2_CLONE
NIMBUS_TARGET_AVX2 void forward_block_avx2(const Net<float>& n, const float* x, int64_t rows, float* z1, float* z2,
                                           float* h1, float* h2, float* at, float* a) {
  forward_block(n, x, rows, z1, z2, h1, h2, at, a);
}
NIMBUS_TARGET_AVX2 void backward_block_avx2(const Net<float>& n, const float* x, int64_t rows, const float* z1,
                                            const float* z2, const float* a, const float* ga, float* sc, float* go,
                                            Grads<float>& acc) {
  backward_block(n, x, rows, z1, z2, a, ga, sc, go, acc);
}
#endif

void run_forward(const Net<float>& n, const float* x, int64_t rows, float* z1, float* z2, float* h1, float* h2,
                 float* at, float* a) {
#ifdef NIMBUS_HAS_AVX2_CLONE
  if (cpu_has_avx2()) return forward_block_avx2(n, x, rows, z1, z2, h1, h2, at, a);
#endif
  forward_block_generic(n, x, rows, z1, z2, h1, h2, at, a);
}
void run_forward(const Net<double>& n, const double* x, int64_t rows, double* z1, double* z2, double* h1,
                 double* h2, double* at, double* a) {
  forward_block(n, x, rows, z1, z2, h1, h2, at, a);
}
void run_backward(const Net<float>& n, const float* x, int64_t rows, const float* z1, const float* z2,
                  const float* a, const float* ga, float* sc, float* go, Grads<float>& acc) {
#ifdef NIMBUS_HAS_AVX2_CLONE
  if (cpu_has_avx2()) return backward_block_avx2(n, x, rows, z1, z2, a, ga, sc, go, acc);
#endif
  backward_block_generic(n, x, rows, z1, z2, a, ga, sc, go, acc);
}
void run_backward(const Net<double>& n, const double* x, int64_t rows, const double* z1, const double* z2,
                  const double* a, const double* ga, double* sc, double* go, Grads<double>& acc) {
  backward_block(n, x, rows, z1, z2, a, ga, sc, go, acc);
}

void check_inputs(const at::Tensor& x, const at::Tensor& w1, const at::Tensor& b1, const at::Tensor& w2,
                  const at::Tensor& b2, const at::Tensor& w3, const at::Tensor& b3, const at::Tensor& base) {
  TORCH_CHECK(x.dim() == 2 && w1.dim() == 2 && w2.dim() == 2 && w3.dim() == 2, "x and the weights must be 2-D");
  const int64_t I = x.size(1), H = w1.size(0), O = w3.size(0);
  TORCH_CHECK(w1.size(1) == I && w2.size(0) == H && w2.size(1) == H && w3.size(1) == H,
              "weights must be W1 [H, I], W2 [H, H], W3 [O, H] for x [P, I]");
  TORCH_CHECK(b1.numel() == H && b2.numel() == H && b3.numel() == O && base.numel() == O,
              "biases must be b1 [H], b2 [H], b3 [O] and base [O]");
  for (const at::Tensor* t : {&x, &w1, &b1, &w2, &b2, &w3, &b3, &base}) {
    TORCH_CHECK(t->device().is_cpu(), "airlight kernel: CPU tensors expected");
    TORCH_CHECK(t->scalar_type() == x.scalar_type(), "airlight kernel: all tensors must share one dtype");
    TORCH_CHECK(t->is_contiguous(), "airlight kernel: contiguous tensors expected");
  }
}

template <typename T>
Net<T> make_net(const at::Tensor& w1t, const at::Tensor& b1, const at::Tensor& w2, const at::Tensor& w2t,
                const at::Tensor& b2, const at::Tensor& w3, const at::Tensor& b3, const at::Tensor& base) {
  return Net<T>{w1t.size(0), w1t.size(1), w3.size(0), w1t.data_ptr<T>(), b1.data_ptr<T>(), w2.data_ptr<T>(),
                w2t.data_ptr<T>(), b2.data_ptr<T>(), w3.data_ptr<T>(), b3.data_ptr<T>(), base.data_ptr<T>()};
}

// (A [P, O], z1 [P, H], z2 [P, H]).
std::tuple<at::Tensor, at::Tensor, at::Tensor> airlight_forward(const at::Tensor& x, const at::Tensor& w1,
                                                                const at::Tensor& b1, const at::Tensor& w2,
                                                                const at::Tensor& b2, const at::Tensor& w3,
                                                                const at::Tensor& b3, const at::Tensor& base) {
  check_inputs(x, w1, b1, w2, b2, w3, b3, base);
  const int64_t P = x.size(0), H = w1.size(0), O = w3.size(0);
  const at::Tensor w1t = w1.t().contiguous(), w2t = w2.t().contiguous();
  at::Tensor a = at::empty({P, O}, x.options()), z1 = at::empty({P, H}, x.options()),
             z2 = at::empty({P, H}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "airlight_forward", [&] {
    using T = scalar_t;
    const Net<T> n = make_net<T>(w1t, b1, w2, w2t, b2, w3, b3, base);
    const T* xp = x.data_ptr<T>();
    T *ap = a.data_ptr<T>(), *z1p = z1.data_ptr<T>(), *z2p = z2.data_ptr<T>();
    const int64_t blocks = (P + kRows - 1) / kRows;
    at::parallel_for(0, blocks, 1, [&](int64_t b, int64_t e) {
      std::vector<T> scratch(2 * kRows * H + O * kRows);
      T* s = scratch.data();
      for (int64_t blk = b; blk < e; ++blk) {
        const int64_t r0 = blk * kRows, rows = std::min(kRows, P - r0);
        run_forward(n, xp + r0 * n.I, rows, z1p + r0 * H, z2p + r0 * H, s, s + kRows * H, s + 2 * kRows * H,
                    ap + r0 * O);
      }
    });
  });
  return {a, z1, z2};
}

// (dW1, db1, dW2, db2, dW3, db3) for the gradient grad_a [P, O] of A.
std::vector<at::Tensor> airlight_backward(const at::Tensor& x, const at::Tensor& w1, const at::Tensor& b1,
                                          const at::Tensor& w2, const at::Tensor& b2, const at::Tensor& w3,
                                          const at::Tensor& b3, const at::Tensor& base, const at::Tensor& z1,
                                          const at::Tensor& z2, const at::Tensor& a, const at::Tensor& grad_a) {
  check_inputs(x, w1, b1, w2, b2, w3, b3, base);
  const int64_t P = x.size(0), I = x.size(1), H = w1.size(0), O = w3.size(0);
  for (const at::Tensor* t : {&z1, &z2, &a, &grad_a}) {
    TORCH_CHECK(t->is_contiguous() && t->scalar_type() == x.scalar_type() && t->device().is_cpu(),
                "airlight kernel: contiguous CPU tensors of one dtype expected");
  }
  TORCH_CHECK(z1.numel() == P * H && z2.numel() == P * H && a.numel() == P * O && grad_a.numel() == P * O,
              "z1, z2 must be [P, H] and A, grad_a [P, O]");
  const at::Tensor w1t = w1.t().contiguous(), w2t = w2.t().contiguous();
  std::vector<at::Tensor> out;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "airlight_backward", [&] {
    using T = scalar_t;
    const Net<T> n = make_net<T>(w1t, b1, w2, w2t, b2, w3, b3, base);
    const T *xp = x.data_ptr<T>(), *z1p = z1.data_ptr<T>(), *z2p = z2.data_ptr<T>(), *ap = a.data_ptr<T>(),
            *gp = grad_a.data_ptr<T>();
    const int64_t blocks = (P + kRows - 1) / kRows;
    const int64_t parts = std::max<int64_t>(1, std::min<int64_t>(kMaxParts, P / kMinRowsPerPart));
    std::vector<Grads<T>> acc(parts, Grads<T>(n));
    auto work = [&](int64_t wb, int64_t we) {
      std::vector<T> scratch(5 * kRows * H + kRows * O);
      T* s = scratch.data();
      for (int64_t w = wb; w < we; ++w) {
        for (int64_t blk = blocks * w / parts; blk < blocks * (w + 1) / parts; ++blk) {
          const int64_t r0 = blk * kRows, rows = std::min(kRows, P - r0);
          run_backward(n, xp + r0 * I, rows, z1p + r0 * H, z2p + r0 * H, ap + r0 * O, gp + r0 * O, s,
                       s + 5 * kRows * H, acc[w]);
        }
      }
    };
    if (parts == 1) {
      work(0, 1);  // parallel_for over a range of 1 would still wake the whole pool
    } else {
      at::parallel_for(0, parts, 1, work);
    }
    for (int64_t w = 1; w < parts; ++w) acc[0].add(acc[w]);
    const Grads<T>& g = acc[0];
    auto tensor = [&](const std::vector<T>& v, at::IntArrayRef shape) {
      at::Tensor t = at::empty(shape, x.options());
      std::copy(v.begin(), v.end(), t.data_ptr<T>());
      return t;
    };
    out = {tensor(g.w1t, {I, H}).t().contiguous(), tensor(g.b1, {H}), tensor(g.w2, {H, H}), tensor(g.b2, {H}),
           tensor(g.w3, {O, H}), tensor(g.b3, {O})};
  });
  return out;
}

}  // namespace
}  // namespace nimbus_airlight

TORCH_LIBRARY(nimbus_airlight, m) {
  m.def("airlight_forward", &nimbus_airlight::airlight_forward);
  m.def("airlight_backward", &nimbus_airlight::airlight_backward);
}
