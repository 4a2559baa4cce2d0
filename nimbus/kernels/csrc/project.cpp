// CPU projection + SH shading (forward and hand-written backward) and tile binning.
//
// The same mathematics as nimbus/render/projection.py (EWA projection with near/far
// culling, FoV-clamped Jacobian, 2D dilation, 3-sigma radius), nimbus/render/sh.py
// (max(SH(dir) + 0.5, 0), 3DGS basis) and nimbus/render/binning.py (tile rectangles,
// lists grouped by tile, front to back, depth ties broken by index), fused into one
// pass over the Gaussians so a render does not pay for ~100 small torch ops and their
// autograd records.  Per-Gaussian maths runs in double whatever the tensors' dtype (it
// is a few hundred flops per Gaussian), eight Gaussians at a time (below); results are
// rounded to the dtype at the end.
//
// Outputs are per Gaussian over ALL N (zeros where culled), so the compositor's
// gradients land on the N Gaussians directly, without gathers and scatters.  Colours
// and opacities are zero for Gaussians with radius 0 (they are never composited).  The
// backward does no maths for a culled Gaussian that no gradient reaches (most of a
// view's): its gradients are zeros.
//
// Registered as torch.ops.nimbus_project.*; built together with composite.cpp into the
// rasterizer extension by nimbus/kernels/raster.py.

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
#include <numeric>
#include <type_traits>
#include <tuple>
#include <vector>

#include "common.h"

namespace nimbus_composite {
int active_isa_index();  // composite.cpp: the clone in use
}  // namespace nimbus_composite

namespace nimbus_project {
namespace {

using namespace nimbus_simd;

// SH constants of nimbus/render/sh.py.
constexpr double C0 = 0.28209479177387814;
constexpr double C1 = 0.4886025119029199;
constexpr double C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                          0.5462742152960396};
constexpr double C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                          -0.4570457994644658, 1.445305721320277, -0.5900435899266435};
// Clamps of the torch path: quaternion and view-direction norms, int32-safe radius.
constexpr double kMinNorm = 1e-12;
constexpr double kMaxRadius = 1073741824.0;  // 2^30

struct Camera {
  double R[9], t[3], fx, fy, cx, cy;
  double lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg;
  double campos[3];  // -R^T t
  double near, far, eps2d, radius_sigmas;
  int64_t width, height, degree;
};

Camera make_camera(const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
                   int64_t degree, double near, double far, double eps2d, double fov_clamp,
                   double radius_sigmas) {
  TORCH_CHECK(viewmat.sizes() == at::IntArrayRef({4, 4}) && K.sizes() == at::IntArrayRef({3, 3}),
              "viewmat must be [4, 4] and K [3, 3]");
  const at::Tensor vm = viewmat.to(at::kDouble).contiguous(), k = K.to(at::kDouble).contiguous();
  const double* v = vm.data_ptr<double>();
  const double* kk = k.data_ptr<double>();
  Camera c{};
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) c.R[3 * i + j] = v[4 * i + j];
    c.t[i] = v[4 * i + 3];
  }
  c.fx = kk[0];
  c.fy = kk[4];
  c.cx = kk[2];
  c.cy = kk[5];
  const double w = static_cast<double>(width), h = static_cast<double>(height);
  c.lim_x_pos = (w - c.cx) / c.fx + (fov_clamp - 1) * 0.5 * w / c.fx;
  c.lim_x_neg = c.cx / c.fx + (fov_clamp - 1) * 0.5 * w / c.fx;
  c.lim_y_pos = (h - c.cy) / c.fy + (fov_clamp - 1) * 0.5 * h / c.fy;
  c.lim_y_neg = c.cy / c.fy + (fov_clamp - 1) * 0.5 * h / c.fy;
  for (int j = 0; j < 3; ++j) c.campos[j] = -(c.R[j] * c.t[0] + c.R[3 + j] * c.t[1] + c.R[6 + j] * c.t[2]);
  c.near = near;
  c.far = far;
  c.eps2d = eps2d;
  c.radius_sigmas = radius_sigmas;
  c.width = width;
  c.height = height;
  c.degree = degree;
  return c;
}

// The per-Gaussian maths runs kLanes (8) Gaussians at a time in float64 vectors (GCC
// vector extensions, common.h), compiled for generic x86-64, AVX2 and AVX-512 like the
// compositing tiles, and the clone follows the compositor's (NIMBUS_CPU_ISA).  Every
// lane runs the IEEE operations of the former one-Gaussian-at-a-time code in the same
// order (no FMA contraction; exp, ceil and sqrt per lane with the same libm and
// instructions), so the outputs are bitwise those of that code on any clone (but for the
// signed zeros of the Gaussians the backward skips).  Branches became selects: a lane's
// result is taken only where the scalar code computed it.  The colour sums stay one
// Gaussian at a time: its coefficients are one contiguous row, and a gather of eight rows
// cost more than the vector arithmetic saved.
using VD = Vec<double>;
using MD = Mask<double>;

// Everything the forward computes for kLanes in-depth Gaussians, kept for the backward.
struct Geo {
  VD p[3];       // camera-frame centre
  VD qn[4];      // normalised quaternion
  VD qnorm;      // |q| before the clamp
  VD Rq[9];      // rotation of the normalised quaternion
  VD s[3];       // scales
  VD T[6];       // J R, 2 x 3
  VD V[6];       // T Rq diag(s), 2 x 3
  VD cxx, cxy, cyy, det;
  VD u, v;
  VD rx, ry;     // x / z and y / z before the FoV clamp
  VD tx, ty;     // z * clamped ratios
  MD mx, my;     // whether the clamp passes the gradient (inside or on the limit)
};

NIMBUS_INLINE VD vsqrt(VD x) {
  VD r;
  for (int l = 0; l < kLanes; ++l) r[l] = std::sqrt(x[l]);
  return r;
}

// The kLanes Gaussians of a block: each lane's index and how many are real (the rest repeat
// the last one and are never written back).
struct Block {
  int64_t idx[kLanes];
  int count;
  // Up to kLanes indices from a list.
  Block(const int64_t* list, int64_t n) : count(static_cast<int>(std::min<int64_t>(kLanes, n))) {
    for (int l = 0; l < kLanes; ++l) idx[l] = list[std::min(l, count - 1)];
  }
  // exp of column j of a row-major [N, width] array (negated first if asked), as float64 lanes.  Called
  // before any vector is live: a libm call in the middle of the vector code would spill them all.
  template <typename S>
  NIMBUS_INLINE VD exp_col(const S* a, int64_t width, int64_t j, bool negate) const {
    double r[kLanes];
    for (int l = 0; l < kLanes; ++l) {
      const double v = double(a[idx[l] * width + j]);
      r[l] = std::exp(negate ? -v : v);
    }
    return load<VD>(r);
  }
  // Column j of a row-major [N, width] array, as float64 lanes.
  template <typename S>
  NIMBUS_INLINE VD col(const S* a, int64_t width, int64_t j) const {
    VD v;
    for (int l = 0; l < kLanes; ++l) v[l] = double(a[idx[l] * width + j]);
    return v;
  }
};

// Whether Gaussian i's centre lies inside the depth range (the cull both passes start with).
template <typename S>
NIMBUS_INLINE bool in_depth(const Camera& c, const S* means, int64_t i) {
  const double z0 = c.R[6] * double(means[3 * i]) + c.R[7] * double(means[3 * i + 1]) +
                    c.R[8] * double(means[3 * i + 2]) + c.t[2];
  return z0 > c.near && z0 < c.far;
}

// scale: exp(log_scale), computed beforehand (Block::exp_col).
NIMBUS_INLINE void geometry(const Camera& c, const VD m[3], const VD q[4], const VD scale[3], Geo& g) {
  for (int i = 0; i < 3; ++i) g.p[i] = c.R[3 * i] * m[0] + c.R[3 * i + 1] * m[1] + c.R[3 * i + 2] * m[2] + c.t[i];
  const VD x = g.p[0], y = g.p[1], z = g.p[2];
  g.u = c.fx * x / z + c.cx;
  g.v = c.fy * y / z + c.cy;
  g.rx = x / z;
  g.ry = y / z;
  const VD crx = vmin(vmax(g.rx, splat(-c.lim_x_neg)), splat(c.lim_x_pos));
  const VD cry = vmin(vmax(g.ry, splat(-c.lim_y_neg)), splat(c.lim_y_pos));
  g.mx = (g.rx >= -c.lim_x_neg) & (g.rx <= c.lim_x_pos);
  g.my = (g.ry >= -c.lim_y_neg) & (g.ry <= c.lim_y_pos);
  g.tx = z * crx;
  g.ty = z * cry;
  const VD J00 = c.fx / z, J02 = -c.fx * g.tx / (z * z), J11 = c.fy / z, J12 = -c.fy * g.ty / (z * z);
  for (int j = 0; j < 3; ++j) {
    g.T[j] = J00 * c.R[j] + J02 * c.R[6 + j];
    g.T[3 + j] = J11 * c.R[3 + j] + J12 * c.R[6 + j];
  }
  g.qnorm = vsqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  const VD qd = vmax(g.qnorm, splat(kMinNorm));
  for (int i = 0; i < 4; ++i) g.qn[i] = q[i] / qd;
  const VD w = g.qn[0], qx = g.qn[1], qy = g.qn[2], qz = g.qn[3];
  const VD R[9] = {1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy),
                   2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx),
                   2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)};
  for (int k = 0; k < 9; ++k) g.Rq[k] = R[k];
  for (int j = 0; j < 3; ++j) g.s[j] = scale[j];
  for (int r = 0; r < 2; ++r) {
    for (int j = 0; j < 3; ++j) {
      g.V[3 * r + j] = (g.T[3 * r] * R[j] + g.T[3 * r + 1] * R[3 + j] + g.T[3 * r + 2] * R[6 + j]) * g.s[j];
    }
  }
  g.cxx = g.V[0] * g.V[0] + g.V[1] * g.V[1] + g.V[2] * g.V[2] + c.eps2d;
  g.cxy = g.V[0] * g.V[3] + g.V[1] * g.V[4] + g.V[2] * g.V[5];
  g.cyy = g.V[3] * g.V[3] + g.V[4] * g.V[4] + g.V[5] * g.V[5] + c.eps2d;
  g.det = g.cxx * g.cyy - g.cxy * g.cxy;
}

// SH basis (and, when grad is given, its derivatives d B_k / d (x, y, z)) at unit directions.
NIMBUS_INLINE void sh_basis(int64_t degree, const VD* d, VD* B, VD (*dB)[3]) {
  const VD x = d[0], y = d[1], z = d[2], zero = splat(0.0);
  B[0] = splat(C0);
  if (dB) dB[0][0] = dB[0][1] = dB[0][2] = zero;
  if (degree >= 1) {
    B[1] = -C1 * y;
    B[2] = C1 * z;
    B[3] = -C1 * x;
    if (dB) {
      const double g[3][3] = {{0, -C1, 0}, {0, 0, C1}, {-C1, 0, 0}};
      for (int k = 0; k < 3; ++k)
        for (int j = 0; j < 3; ++j) dB[1 + k][j] = splat(g[k][j]);
    }
  }
  if (degree >= 2) {
    const VD xx = x * x, yy = y * y, zz = z * z;
    B[4] = C2[0] * x * y;
    B[5] = C2[1] * y * z;
    B[6] = C2[2] * (2.0 * zz - xx - yy);
    B[7] = C2[3] * x * z;
    B[8] = C2[4] * (xx - yy);
    if (dB) {
      const VD g[5][3] = {{C2[0] * y, C2[0] * x, zero},
                          {zero, C2[1] * z, C2[1] * y},
                          {-2 * C2[2] * x, -2 * C2[2] * y, 4 * C2[2] * z},
                          {C2[3] * z, zero, C2[3] * x},
                          {2 * C2[4] * x, -2 * C2[4] * y, zero}};
      for (int k = 0; k < 5; ++k)
        for (int j = 0; j < 3; ++j) dB[4 + k][j] = g[k][j];
    }
    if (degree >= 3) {
      B[9] = C3[0] * y * (3 * xx - yy);
      B[10] = C3[1] * x * y * z;
      B[11] = C3[2] * y * (4 * zz - xx - yy);
      B[12] = C3[3] * z * (2 * zz - 3 * xx - 3 * yy);
      B[13] = C3[4] * x * (4 * zz - xx - yy);
      B[14] = C3[5] * z * (xx - yy);
      B[15] = C3[6] * x * (xx - 3 * yy);
      if (dB) {
        const VD g[7][3] = {{C3[0] * 6 * x * y, C3[0] * (3 * xx - 3 * yy), zero},
                            {C3[1] * y * z, C3[1] * x * z, C3[1] * x * y},
                            {C3[2] * -2 * x * y, C3[2] * (4 * zz - xx - 3 * yy), C3[2] * 8 * y * z},
                            {C3[3] * -6 * x * z, C3[3] * -6 * y * z, C3[3] * (6 * zz - 3 * xx - 3 * yy)},
                            {C3[4] * (4 * zz - 3 * xx - yy), C3[4] * -2 * x * y, C3[4] * 8 * x * z},
                            {C3[5] * 2 * x * z, C3[5] * -2 * y * z, C3[5] * (xx - yy)},
                            {C3[6] * (3 * xx - 3 * yy), C3[6] * -6 * x * y, zero}};
        for (int k = 0; k < 7; ++k)
          for (int j = 0; j < 3; ++j) dB[9 + k][j] = g[k][j];
      }
    }
  }
}


void check_params(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& log_scales,
                  const at::Tensor& logits, const at::Tensor& sh_dc, const at::Tensor& sh_rest, int64_t degree) {
  const int64_t N = means.size(0);
  const auto dtype = means.scalar_type();
  for (const at::Tensor* x : {&means, &quats, &log_scales, &logits, &sh_dc, &sh_rest}) {
    TORCH_CHECK(x->device().is_cpu() && x->scalar_type() == dtype && x->is_contiguous(),
                "project_cpp: inputs must be contiguous CPU tensors of one dtype");
  }
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3, "means must be [N, 3]");
  TORCH_CHECK(quats.sizes() == at::IntArrayRef({N, 4}), "quats must be [N, 4]");
  TORCH_CHECK(log_scales.sizes() == at::IntArrayRef({N, 3}), "log_scales must be [N, 3]");
  TORCH_CHECK(logits.sizes() == at::IntArrayRef({N}), "opacity_logits must be [N]");
  TORCH_CHECK(sh_dc.sizes() == at::IntArrayRef({N, 1, 3}), "sh_dc must be [N, 1, 3]");
  TORCH_CHECK(sh_rest.dim() == 3 && sh_rest.size(0) == N && sh_rest.size(2) == 3, "sh_rest must be [N, K, 3]");
  TORCH_CHECK(degree >= 0 && degree <= 3 && (degree + 1) * (degree + 1) - 1 <= sh_rest.size(1),
              "sh_degree must be in 0..3 and within the stored bands");
}

// The inputs both passes read, and the forward's outputs.
template <typename S>
struct Params {
  const S *pm, *pq, *ps, *pl, *pdc, *prest;
  int64_t KR, nb;
};
template <typename S>
struct ForwardOut {
  S *om, *oc, *ocol, *oo, *oz;
  int32_t* orad;
};

// The forward of Gaussians [b, e).
template <typename S>
NIMBUS_INLINE void range_impl(const Camera& c, const Params<S>& P, const ForwardOut<S>& O, int64_t b, int64_t e) {
  const int64_t degree = c.degree, nb = P.nb, KR = P.KR;
  const VD zero = splat(0.0);
  Geo g;
  VD B[16];
  // Gaussians outside the depth range get zeros; the rest are gathered and run kLanes at a time.
  std::vector<int64_t> live;
  live.reserve(static_cast<size_t>(e - b));
  for (int64_t i = b; i < e; ++i) {
    if (in_depth(c, P.pm, i)) {
      live.push_back(i);
      continue;
    }
    for (int j = 0; j < 2; ++j) O.om[2 * i + j] = 0;
    for (int j = 0; j < 3; ++j) O.oc[3 * i + j] = O.ocol[3 * i + j] = 0;
    O.oo[i] = O.oz[i] = 0;
    O.orad[i] = 0;
  }
  const int64_t n_live = static_cast<int64_t>(live.size());
  for (int64_t p0 = 0; p0 < n_live; p0 += kLanes) {
    const Block blk(live.data() + p0, n_live - p0);
    VD m[3], q[4], scale[3];
    for (int j = 0; j < 3; ++j) scale[j] = blk.exp_col(P.ps, 3, j, false);
    const VD e_logit = blk.exp_col(P.pl, 1, 0, true);
    for (int j = 0; j < 3; ++j) m[j] = blk.col(P.pm, 3, j);
    for (int j = 0; j < 4; ++j) q[j] = blk.col(P.pq, 4, j);
    geometry(c, m, q, scale, g);
    const VD mid = 0.5 * (g.cxx + g.cyy);
    const VD lam = mid + vsqrt(vmax(mid * mid - g.det, zero));
    const VD r_unrounded = c.radius_sigmas * vsqrt(lam);
    const VD opac = 1.0 / (1.0 + e_logit);
    VD dir[3] = {zero, zero, zero};
    if (degree > 0) {
      VD d[3], n2 = zero;
      for (int j = 0; j < 3; ++j) {
        d[j] = m[j] - c.campos[j];
        n2 += d[j] * d[j];
      }
      const VD nd = vmax(vsqrt(n2), splat(kMinNorm));
      for (int j = 0; j < 3; ++j) dir[j] = d[j] / nd;
    }
    sh_basis(degree, dir, B, nullptr);
    for (int l = 0; l < blk.count; ++l) {
      const int64_t i = blk.idx[l];
      O.om[2 * i] = static_cast<S>(g.u[l]);
      O.om[2 * i + 1] = static_cast<S>(g.v[l]);
      O.oz[i] = static_cast<S>(g.p[2][l]);
      O.oc[3 * i] = static_cast<S>(g.cyy[l] / g.det[l]);
      O.oc[3 * i + 1] = static_cast<S>(-g.cxy[l] / g.det[l]);
      O.oc[3 * i + 2] = static_cast<S>(g.cxx[l] / g.det[l]);
      double r = std::ceil(r_unrounded[l]);
      const double u = g.u[l], v = g.v[l];
      const bool on = (u + r > 0) && (u - r < c.width) && (v + r > 0) && (v - r < c.height);
      if (!on || !std::isfinite(r)) r = 0;
      r = std::min(r, kMaxRadius);
      const int32_t rad = static_cast<int32_t>(r);
      O.orad[i] = rad;
      if (rad <= 0) {
        O.oo[i] = 0;
        for (int ch = 0; ch < 3; ++ch) O.ocol[3 * i + ch] = 0;
        continue;
      }
      O.oo[i] = static_cast<S>(opac[l]);
      // The colour one Gaussian at a time: its coefficients are one contiguous row.
      const S* rest = P.prest + i * KR * 3;
      for (int ch = 0; ch < 3; ++ch) {
        double acc = B[0][l] * double(P.pdc[3 * i + ch]);
        for (int64_t k = 1; k < nb; ++k) acc += B[k][l] * double(rest[(k - 1) * 3 + ch]);
        O.ocol[3 * i + ch] = static_cast<S>(std::max(acc + 0.5, 0.0));
      }
    }
  }
}

// The gradients w.r.t. the forward's outputs, and the parameters' gradients.
template <typename S>
struct BackwardIO {
  const int32_t* rad;
  const S *um, *uc, *ucol, *uo, *uz, *sc;  // sc: row_scale, or null
  S *om, *oq, *os, *ol, *odc, *orest;
};

NIMBUS_INLINE VD gJ(const VD* gT, const Camera& c, int r, int k) {
  return gT[3 * r] * c.R[3 * k] + gT[3 * r + 1] * c.R[3 * k + 1] + gT[3 * r + 2] * c.R[3 * k + 2];
}

// The backward of Gaussians [b, e).
template <typename S>
NIMBUS_INLINE void range_impl(const Camera& c, const Params<S>& P, const BackwardIO<S>& O, int64_t b, int64_t e) {
  const int64_t degree = c.degree, nb = P.nb, KR = P.KR;
  const VD zero = splat(0.0);
  Geo g;
  VD B[16], dB[16][3];
  // A Gaussian outside the depth range, or culled (radius 0) with no gradient reaching it, gets
  // zeros without its maths: most of a view's Gaussians are culled.  (Where that maths gives
  // -0 or, for a degenerate culled Gaussian, NaN times 0, the result is +0 now.)  The rest are
  // gathered and run kLanes at a time.
  const auto zero_row = [&](int64_t i) {
    for (int j = 0; j < 3; ++j) O.om[3 * i + j] = O.os[3 * i + j] = O.odc[3 * i + j] = 0;
    for (int j = 0; j < 4; ++j) O.oq[4 * i + j] = 0;
    O.ol[i] = 0;
    S* rrow = O.orest + i * KR * 3;
    for (int64_t k = 0; k < KR * 3; ++k) rrow[k] = 0;
  };
  std::vector<int64_t> live;
  live.reserve(static_cast<size_t>(e - b));
  for (int64_t i = b; i < e; ++i) {
    bool reached = O.rad[i] > 0 || O.uo[i] != 0 || O.uz[i] != 0;
    for (int j = 0; j < 2; ++j) reached = reached || O.um[2 * i + j] != 0;
    for (int j = 0; j < 3; ++j) reached = reached || O.uc[3 * i + j] != 0 || O.ucol[3 * i + j] != 0;
    if (reached && in_depth(c, P.pm, i)) {
      live.push_back(i);
    } else {
      zero_row(i);
    }
  }
  const int64_t n_live = static_cast<int64_t>(live.size());
  for (int64_t p0 = 0; p0 < n_live; p0 += kLanes) {
    const Block blk(live.data() + p0, n_live - p0);
    VD m[3], q[4], scale[3];
    for (int j = 0; j < 3; ++j) scale[j] = blk.exp_col(P.ps, 3, j, false);
    const VD e_logit = blk.exp_col(P.pl, 1, 0, true);
    for (int j = 0; j < 3; ++j) m[j] = blk.col(P.pm, 3, j);
    for (int j = 0; j < 4; ++j) q[j] = blk.col(P.pq, 4, j);
    geometry(c, m, q, scale, g);
    MD vis;
    for (int l = 0; l < kLanes; ++l) vis[l] = O.rad[blk.idx[l]] > 0 ? -1 : 0;
    VD wi;  // x * 1 is x: the unscaled bits when there is no factor
    for (int l = 0; l < kLanes; ++l) wi[l] = O.sc ? double(O.sc[blk.idx[l]]) : 1.0;
    VD gmean[3] = {zero, zero, zero};
    // Colour and opacity (their results are kept for visible Gaussians only).
    const VD o = 1.0 / (1.0 + e_logit);
    const VD ol = blk.col(O.uo, 1, 0) * o * (1 - o);
    VD dir[3] = {zero, zero, zero}, d[3] = {zero, zero, zero}, nd = splat(1.0);
    if (degree > 0) {
      VD n2 = zero;
      for (int j = 0; j < 3; ++j) {
        d[j] = m[j] - c.campos[j];
        n2 += d[j] * d[j];
      }
      nd = vmax(vsqrt(n2), splat(kMinNorm));
      for (int j = 0; j < 3; ++j) dir[j] = d[j] / nd;
    }
    sh_basis(degree, dir, B, dB);
    // The colour one Gaussian at a time (its coefficients are one contiguous row), written here;
    // the direction's gradient goes back into lanes.
    double gdir_l[3][kLanes] = {};
    for (int l = 0; l < blk.count; ++l) {
      if (!vis[l]) continue;
      const int64_t i = blk.idx[l];
      const S wl = static_cast<S>(wi[l]);
      const S* rest = P.prest + i * KR * 3;
      S* orest = O.orest + i * KR * 3;
      double gd[3] = {0, 0, 0};
      for (int ch = 0; ch < 3; ++ch) {
        double acc = B[0][l] * double(P.pdc[3 * i + ch]);
        for (int64_t k = 1; k < nb; ++k) acc += B[k][l] * double(rest[(k - 1) * 3 + ch]);
        // clamp_min passes the gradient where the input is >= the bound.
        const double gc = acc + 0.5 >= 0.0 ? double(O.ucol[3 * i + ch]) : 0.0;
        O.odc[3 * i + ch] = static_cast<S>(B[0][l] * gc) * wl;
        for (int64_t k = 1; k < nb; ++k) {
          orest[(k - 1) * 3 + ch] = static_cast<S>(B[k][l] * gc) * wl;
          const double cf = double(rest[(k - 1) * 3 + ch]) * gc;
          for (int j = 0; j < 3; ++j) gd[j] += cf * dB[k][j][l];
        }
      }
      for (int j = 0; j < 3; ++j) gdir_l[j][l] = gd[j];
    }
    VD gdir[3];
    for (int j = 0; j < 3; ++j) gdir[j] = load<VD>(gdir_l[j]);
    if (degree > 0) {
      // d (d / |d|) = (I - dir dir^T) / |d|; with the norm clamped the Jacobian is I / 1e-12.
      const VD dot = dir[0] * gdir[0] + dir[1] * gdir[1] + dir[2] * gdir[2];
      const MD clamped = vsqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) < kMinNorm;
      for (int j = 0; j < 3; ++j)
        gmean[j] += select(vis, select(clamped, gdir[j] / nd, (gdir[j] - dir[j] * dot) / nd), zero);
    }
    // Conic = inverse of the dilated covariance.
    const VD ga = blk.col(O.uc, 3, 0), gb = blk.col(O.uc, 3, 1), gcc = blk.col(O.uc, 3, 2);
    const VD det = g.det, d2 = det * det, cxx = g.cxx, cxy = g.cxy, cyy = g.cyy;
    const VD g_cxx = ga * (-cyy * cyy / d2) + gb * (cxy * cyy / d2) + gcc * (1.0 / det - cxx * cyy / d2);
    const VD g_cyy = ga * (1.0 / det - cyy * cxx / d2) + gb * (cxy * cxx / d2) + gcc * (-cxx * cxx / d2);
    const VD g_cxy = ga * (2 * cyy * cxy / d2) + gb * (-1.0 / det - 2 * cxy * cxy / d2) + gcc * (2 * cxx * cxy / d2);
    // cov = V V^T.
    VD gV[6];
    for (int j = 0; j < 3; ++j) {
      gV[j] = 2 * g_cxx * g.V[j] + g_cxy * g.V[3 + j];
      gV[3 + j] = 2 * g_cyy * g.V[3 + j] + g_cxy * g.V[j];
    }
    // V = T Rq diag(s): gT = gV (Rq diag(s))^T, gM = T^T gV with M = Rq diag(s).
    VD gT[6] = {zero, zero, zero, zero, zero, zero}, gRq[9], glog[3];
    for (int r = 0; r < 2; ++r)
      for (int k = 0; k < 3; ++k)
        for (int j = 0; j < 3; ++j) gT[3 * r + k] += gV[3 * r + j] * g.Rq[3 * k + j] * g.s[j];
    for (int j = 0; j < 3; ++j) {
      VD gsj = zero;
      for (int k = 0; k < 3; ++k) {
        const VD gM = g.T[k] * gV[j] + g.T[3 + k] * gV[3 + j];
        gRq[3 * k + j] = gM * g.s[j];
        gsj += gM * g.Rq[3 * k + j];
      }
      glog[j] = gsj * g.s[j];
    }
    // T = J R: gJ = gT R^T (entries 00, 02, 11, 12 are the non-constant ones).
    const VD gJ00 = gJ(gT, c, 0, 0), gJ02 = gJ(gT, c, 0, 2), gJ11 = gJ(gT, c, 1, 1), gJ12 = gJ(gT, c, 1, 2);
    const VD x = g.p[0], y = g.p[1], z = g.p[2], z2 = z * z, z3 = z2 * z;
    VD gx = zero, gy = zero, gz = blk.col(O.uz, 1, 0);
    gz += gJ00 * (-c.fx / z2) + gJ11 * (-c.fy / z2) + gJ02 * (2 * c.fx * g.tx / z3) +
          gJ12 * (2 * c.fy * g.ty / z3);
    const VD gtx = gJ02 * (-c.fx / z2), gty = gJ12 * (-c.fy / z2);
    // tx = z clamp(x / z): d/dx = [unclamped], d/dz = clamp(x / z) - [unclamped] x / z.
    gx += select(g.mx, gtx, zero);
    gz += gtx * (g.tx / z - select(g.mx, g.rx, zero));
    gy += select(g.my, gty, zero);
    gz += gty * (g.ty / z - select(g.my, g.ry, zero));
    // Screen centre.
    const VD gu = blk.col(O.um, 2, 0), gv = blk.col(O.um, 2, 1);
    gx += gu * c.fx / z;
    gy += gv * c.fy / z;
    gz += -gu * c.fx * x / z2 - gv * c.fy * y / z2;
    for (int j = 0; j < 3; ++j) gmean[j] += c.R[j] * gx + c.R[3 + j] * gy + c.R[6 + j] * gz;
    // Rotation of the normalised quaternion.
    const VD w = g.qn[0], qx = g.qn[1], qy = g.qn[2], qz = g.qn[3];
    const VD* G = gRq;
    VD gqn[4];
    gqn[0] = 2 * (-qz * G[1] + qy * G[2] + qz * G[3] - qx * G[5] - qy * G[6] + qx * G[7]);
    gqn[1] = 2 * (qy * G[1] + qz * G[2] + qy * G[3] - 2 * qx * G[4] - w * G[5] + qz * G[6] + w * G[7] -
                  2 * qx * G[8]);
    gqn[2] = 2 * (-2 * qy * G[0] + qx * G[1] + w * G[2] + qx * G[3] + qz * G[5] - w * G[6] + qz * G[7] -
                  2 * qy * G[8]);
    gqn[3] = 2 * (-2 * qz * G[0] - w * G[1] + qx * G[2] + w * G[3] - 2 * qz * G[4] + qy * G[5] + qx * G[6] +
                  qy * G[7]);
    const MD unit = g.qnorm > kMinNorm;
    const VD qdot = gqn[0] * g.qn[0] + gqn[1] * g.qn[1] + gqn[2] * g.qn[2] + gqn[3] * g.qn[3];
    VD gq[4];
    for (int j = 0; j < 4; ++j) gq[j] = select(unit, (gqn[j] - g.qn[j] * qdot) / g.qnorm, gqn[j] / kMinNorm);
    // Write the real lanes: colour and opacity for visible Gaussians only.
    const int64_t n_rest = (nb - 1) * 3;
    for (int l = 0; l < blk.count; ++l) {
      const int64_t i = blk.idx[l];
      S* rrow = O.orest + i * KR * 3;
      const S wl = static_cast<S>(wi[l]);
      for (int j = 0; j < 3; ++j) O.om[3 * i + j] = static_cast<S>(gmean[j][l]) * wl;
      for (int j = 0; j < 3; ++j) O.os[3 * i + j] = static_cast<S>(glog[j][l]) * wl;
      for (int j = 0; j < 4; ++j) O.oq[4 * i + j] = static_cast<S>(gq[j][l]) * wl;
      int64_t k0 = 0;
      if (vis[l]) {  // odc and the first bands of rrow were written with the colour
        O.ol[i] = static_cast<S>(ol[l]) * wl;
        k0 = n_rest;
      } else {
        O.ol[i] = 0;
        for (int ch = 0; ch < 3; ++ch) O.odc[3 * i + ch] = 0;
      }
      for (int64_t k = k0; k < KR * 3; ++k) rrow[k] = 0;
    }
  }
}

// The clones, one set for both passes (range_impl is overloaded on the pass's output struct).  One
// range of Gaussians per call (a parallel_for chunk), so the switch is paid once per chunk.
template <typename S, typename Out>
void range_generic(const Camera& c, const Params<S>& P, const Out& O, int64_t b, int64_t e) {
  range_impl(c, P, O, b, e);
}
#ifdef NIMBUS_HAS_AVX2_CLONE
template <typename S, typename Out>
NIMBUS_TARGET_AVX2 void range_avx2(const Camera& c, const Params<S>& P, const Out& O, int64_t b, int64_t e) {
  range_impl(c, P, O, b, e);
}
#endif
#ifdef NIMBUS_HAS_AVX512_CLONE
template <typename S, typename Out>
NIMBUS_TARGET_AVX512 void range_avx512(const Camera& c, const Params<S>& P, const Out& O, int64_t b, int64_t e) {
  range_impl(c, P, O, b, e);
}
#endif
// Gaussians [b, e) of one pass, on the compositor's clone.
template <typename S, typename Out>
void run_range(const Camera& c, const Params<S>& P, const Out& O, int64_t b, int64_t e) {
  switch (nimbus_composite::active_isa_index()) {
#ifdef NIMBUS_HAS_AVX512_CLONE
    case 2:
      return range_avx512(c, P, O, b, e);
#endif
#ifdef NIMBUS_HAS_AVX2_CLONE
    case 1:
      return range_avx2(c, P, O, b, e);
#endif
    default:
      return range_generic(c, P, O, b, e);
  }
}

// Returns means2d [N, 2], conics [N, 3], colors [N, 3], opacities [N], depths [N], radii [N] int32.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> project_forward(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& log_scales, const at::Tensor& logits,
    const at::Tensor& sh_dc, const at::Tensor& sh_rest, const at::Tensor& viewmat, const at::Tensor& K,
    int64_t width, int64_t height, int64_t degree, double near, double far, double eps2d, double fov_clamp,
    double radius_sigmas) {
  check_params(means, quats, log_scales, logits, sh_dc, sh_rest, degree);
  const Camera c = make_camera(viewmat, K, width, height, degree, near, far, eps2d, fov_clamp, radius_sigmas);
  const int64_t N = means.size(0), KR = sh_rest.size(1), nb = (degree + 1) * (degree + 1);
  const auto opts = means.options();
  at::Tensor means2d = at::empty({N, 2}, opts), conics = at::empty({N, 3}, opts);
  at::Tensor colors = at::empty({N, 3}, opts), opac = at::empty({N}, opts), depths = at::empty({N}, opts);
  at::Tensor radii = at::empty({N}, opts.dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_forward", [&] {
    using S = scalar_t;
    const S *pm = means.data_ptr<S>(), *pq = quats.data_ptr<S>(), *ps = log_scales.data_ptr<S>();
    const S *pl = logits.data_ptr<S>(), *pdc = sh_dc.data_ptr<S>(), *prest = sh_rest.data_ptr<S>();
    S *om = means2d.data_ptr<S>(), *oc = conics.data_ptr<S>(), *ocol = colors.data_ptr<S>();
    S *oo = opac.data_ptr<S>(), *oz = depths.data_ptr<S>();
    int32_t* orad = radii.data_ptr<int32_t>();
    const Params<S> P{pm, pq, ps, pl, pdc, prest, KR, nb};
    const ForwardOut<S> O{om, oc, ocol, oo, oz, orad};
    at::parallel_for(0, N, 8192, [&](int64_t b, int64_t e) { run_range(c, P, O, b, e); });
  });
  return {means2d, conics, colors, opac, depths, radii};
}

// Gradients w.r.t. means [N, 3], quats [N, 4], log_scales [N, 3], opacity_logits [N],
// sh_dc [N, 1, 3] and sh_rest [N, K, 3] (bands above the degree get zero), given those
// w.r.t. the outputs of project_forward.  row_scale: empty, or [N] factors of the dtype
// that multiply every gradient of Gaussian i as it is written: each stored value is the
// unscaled one rounded to the dtype, times the factor, in the dtype (the bits of scaling
// the returned gradients afterwards, without the extra pass over them).  Entries the loop
// leaves at zero (culled rows, bands above the degree) stay zero: equal for finite factors.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> project_backward(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& log_scales, const at::Tensor& logits,
    const at::Tensor& sh_dc, const at::Tensor& sh_rest, const at::Tensor& viewmat, const at::Tensor& K,
    int64_t width, int64_t height, int64_t degree, double near, double far, double eps2d, double fov_clamp,
    double radius_sigmas, const at::Tensor& radii, const at::Tensor& g_means2d, const at::Tensor& g_conics,
    const at::Tensor& g_colors, const at::Tensor& g_opac, const at::Tensor& g_depths, const at::Tensor& row_scale) {
  check_params(means, quats, log_scales, logits, sh_dc, sh_rest, degree);
  const Camera c = make_camera(viewmat, K, width, height, degree, near, far, eps2d, fov_clamp, radius_sigmas);
  const int64_t N = means.size(0), KR = sh_rest.size(1), nb = (degree + 1) * (degree + 1);
  TORCH_CHECK(radii.scalar_type() == at::kInt && radii.is_contiguous() && radii.size(0) == N,
              "radii must be [N] int32");
  const auto dtype = means.scalar_type();
  for (const at::Tensor* x : {&g_means2d, &g_conics, &g_colors, &g_opac, &g_depths}) {
    TORCH_CHECK(x->scalar_type() == dtype && x->is_contiguous() && x->size(0) == N,
                "project_backward: output gradients must be contiguous [N, ...] tensors of the inputs' dtype");
  }
  const bool scaled = row_scale.numel() > 0;
  TORCH_CHECK(!scaled || (row_scale.scalar_type() == dtype && row_scale.is_contiguous() && row_scale.dim() == 1 &&
                          row_scale.size(0) == N && row_scale.device().is_cpu()),
              "project_backward: row_scale must be empty or a contiguous CPU [N] tensor of the inputs' dtype");
  const auto opts = means.options();
  at::Tensor gm = at::empty({N, 3}, opts), gq = at::empty({N, 4}, opts), gs = at::empty({N, 3}, opts);
  at::Tensor gl = at::empty({N}, opts), gdc = at::empty({N, 1, 3}, opts), grest = at::empty({N, KR, 3}, opts);
  AT_DISPATCH_FLOATING_TYPES(dtype, "project_backward", [&] {
    using S = scalar_t;
    const S *pm = means.data_ptr<S>(), *pq = quats.data_ptr<S>(), *ps = log_scales.data_ptr<S>();
    const S *pl = logits.data_ptr<S>(), *pdc = sh_dc.data_ptr<S>(), *prest = sh_rest.data_ptr<S>();
    const int32_t* rad = radii.data_ptr<int32_t>();
    const S *um = g_means2d.data_ptr<S>(), *uc = g_conics.data_ptr<S>(), *ucol = g_colors.data_ptr<S>();
    const S *uo = g_opac.data_ptr<S>(), *uz = g_depths.data_ptr<S>();
    S *om = gm.data_ptr<S>(), *oq = gq.data_ptr<S>(), *os = gs.data_ptr<S>(), *ol = gl.data_ptr<S>();
    S *odc = gdc.data_ptr<S>(), *orest = grest.data_ptr<S>();
    const S* sc = scaled ? row_scale.data_ptr<S>() : nullptr;
    const Params<S> P{pm, pq, ps, pl, pdc, prest, KR, nb};
    const BackwardIO<S> O{rad, um, uc, ucol, uo, uz, sc, om, oq, os, ol, odc, orest};
    at::parallel_for(0, N, 8192, [&](int64_t b, int64_t e) { run_range(c, P, O, b, e); });
  });
  return {gm, gq, gs, gl, gdc, grest};
}

// Reorders `order` (Gaussian indices, ascending) by depth, ties kept in index order: what
// std::stable_sort with z[a] < z[b] gives, by a least-significant-digit radix sort of the
// depths' bits (a byte a pass, passes where every key has the same byte skipped), which is
// stable and does not compare.  -0 sorts with +0 (they compare equal); NaN sorts last, as
// with torch.sort (a comparison sort has no defined place for it).
template <typename S>
void sort_by_depth(std::vector<int64_t>& order, const S* z) {
  using U = typename std::conditional<sizeof(S) == 4, uint32_t, uint64_t>::type;
  constexpr U kSign = U(1) << (8 * sizeof(U) - 1);
  const size_t n = order.size();
  std::vector<U> key(n), key2(n);
  std::vector<int64_t> order2(n);
  for (size_t k = 0; k < n; ++k) {
    S v = z[order[k]];
    if (v == S(0)) v = S(0);
    U b;
    std::memcpy(&b, &v, sizeof(b));
    key[k] = v != v ? ~U(0) : (b & kSign) ? ~b : (b | kSign);  // the float order as unsigned order
  }
  for (int shift = 0; shift < int(8 * sizeof(U)); shift += 8) {
    size_t start[257] = {0};
    for (size_t k = 0; k < n; ++k) ++start[((key[k] >> shift) & 255) + 1];
    if (n == 0 || start[((key[0] >> shift) & 255) + 1] == n) continue;
    for (int d = 0; d < 256; ++d) start[d + 1] += start[d];
    for (size_t k = 0; k < n; ++k) {
      const size_t pos = start[(key[k] >> shift) & 255]++;
      key2[pos] = key[k];
      order2[pos] = order[k];
    }
    key.swap(key2);
    order.swap(order2);
  }
}

// Tile-sorted intersection lists (binning.py's contract) for Gaussians with radius > 0.
// Counting sort by tile of the Gaussians taken in depth order (a radix sort): O(N + I), no sort
// of the I intersections.
std::tuple<at::Tensor, at::Tensor> bin_gaussians(const at::Tensor& means2d, const at::Tensor& radii,
                                                 const at::Tensor& depths, int64_t width, int64_t height,
                                                 int64_t tile) {
  TORCH_CHECK(width > 0 && height > 0 && tile > 0, "width, height and tile_size must be positive");
  const int64_t N = means2d.size(0);
  TORCH_CHECK(means2d.is_contiguous() && means2d.dim() == 2 && means2d.size(1) == 2, "means2d must be [N, 2]");
  TORCH_CHECK(radii.scalar_type() == at::kInt && radii.is_contiguous() && radii.size(0) == N, "radii: [N] int32");
  TORCH_CHECK(depths.scalar_type() == means2d.scalar_type() && depths.is_contiguous() && depths.size(0) == N,
              "depths must be [N] of the means' dtype");
  const int64_t tx = (width + tile - 1) / tile, ty = (height + tile - 1) / tile, T = tx * ty;
  at::Tensor offsets = at::zeros({T + 1}, means2d.options().dtype(at::kLong));
  int64_t* off = offsets.data_ptr<int64_t>();
  std::vector<int32_t> rect(static_cast<size_t>(N) * 4);
  std::vector<int64_t> order;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_gaussians", [&] {
    using S = scalar_t;
    const S* m = means2d.data_ptr<S>();
    const S* z = depths.data_ptr<S>();
    const int32_t* rad = radii.data_ptr<int32_t>();
    // Same float arithmetic as binning.tile_rects, so the rectangles agree exactly.
    const S ts = static_cast<S>(tile);
    at::parallel_for(0, N, 16384, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        int32_t* r = rect.data() + 4 * i;
        r[0] = r[1] = r[2] = r[3] = 0;
        if (rad[i] <= 0) continue;
        const S rr = static_cast<S>(rad[i]);
        const S lo[2] = {std::floor((m[2 * i] - rr) / ts), std::floor((m[2 * i + 1] - rr) / ts)};
        const S hi[2] = {std::ceil((m[2 * i] + rr) / ts), std::ceil((m[2 * i + 1] + rr) / ts)};
        const S lim[2] = {static_cast<S>(tx), static_cast<S>(ty)};
        for (int a = 0; a < 2; ++a) {
          r[a] = static_cast<int32_t>(std::min(std::max(lo[a], S(0)), lim[a]));
          r[2 + a] = static_cast<int32_t>(std::min(std::max(hi[a], S(0)), lim[a]));
        }
      }
    });
    order.reserve(N);
    for (int64_t i = 0; i < N; ++i) {
      const int32_t* r = rect.data() + 4 * i;
      if (r[2] > r[0] && r[3] > r[1]) order.push_back(i);
    }
    sort_by_depth(order, z);
  });
  for (int64_t i : order) {
    const int32_t* r = rect.data() + 4 * i;
    for (int32_t y = r[1]; y < r[3]; ++y)
      for (int32_t x = r[0]; x < r[2]; ++x) ++off[y * tx + x + 1];
  }
  for (int64_t t = 0; t < T; ++t) off[t + 1] += off[t];
  at::Tensor ids = at::empty({off[T]}, means2d.options().dtype(at::kLong));
  int64_t* out = ids.data_ptr<int64_t>();
  std::vector<int64_t> fill(off, off + T);
  for (int64_t i : order) {
    const int32_t* r = rect.data() + 4 * i;
    for (int32_t y = r[1]; y < r[3]; ++y)
      for (int32_t x = r[0]; x < r[2]; ++x) out[fill[y * tx + x]++] = i;
  }
  return {ids, offsets};
}

}  // namespace
}  // namespace nimbus_project

TORCH_LIBRARY(nimbus_project, m) {
  m.def("project_forward", &nimbus_project::project_forward);
  m.def("project_backward", &nimbus_project::project_backward);
  m.def("bin_gaussians", &nimbus_project::bin_gaussians);
}
