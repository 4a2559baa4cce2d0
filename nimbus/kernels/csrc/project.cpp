// CPU projection + SH shading (forward and hand-written backward) and tile binning.
//
// The same mathematics as nimbus/render/projection.py (EWA projection with near/far
// culling, FoV-clamped Jacobian, 2D dilation, 3-sigma radius), nimbus/render/sh.py
// (max(SH(dir) + 0.5, 0), 3DGS basis) and nimbus/render/binning.py (tile rectangles,
// lists grouped by tile, front to back, depth ties broken by index), fused into one
// pass over the Gaussians so a render does not pay for ~100 small torch ops and their
// autograd records.  Per-Gaussian maths runs in double whatever the tensors' dtype (it
// is a few hundred flops per Gaussian); results are rounded to the dtype at the end.
//
// Outputs are per Gaussian over ALL N (zeros where culled), so the compositor's
// gradients land on the N Gaussians directly, without gathers and scatters.  Colours
// and opacities are zero for Gaussians with radius 0 (they are never composited).
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
#include <tuple>
#include <vector>

namespace nimbus_project {
namespace {

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

// Everything the forward computes for one in-depth Gaussian, kept for the backward.
struct Geo {
  double p[3];       // camera-frame centre
  double qn[4];      // normalised quaternion
  double qnorm;      // |q| before the clamp
  double Rq[9];      // rotation of the normalised quaternion
  double s[3];       // scales
  double T[6];       // J R, 2 x 3
  double V[6];       // T Rq diag(s), 2 x 3
  double cxx, cxy, cyy, det;
  double u, v;
  double rx, ry;     // x / z and y / z before the FoV clamp
  double tx, ty;     // z * clamped ratios
  bool mx, my;       // whether the clamp passes the gradient (inside or on the limit)
};

template <typename S>
void geometry(const Camera& c, const S* mean, const S* quat, const S* log_scale, Geo& g) {
  const double m[3] = {double(mean[0]), double(mean[1]), double(mean[2])};
  for (int i = 0; i < 3; ++i) g.p[i] = c.R[3 * i] * m[0] + c.R[3 * i + 1] * m[1] + c.R[3 * i + 2] * m[2] + c.t[i];
  const double x = g.p[0], y = g.p[1], z = g.p[2];
  g.u = c.fx * x / z + c.cx;
  g.v = c.fy * y / z + c.cy;
  g.rx = x / z;
  g.ry = y / z;
  const double crx = std::min(std::max(g.rx, -c.lim_x_neg), c.lim_x_pos);
  const double cry = std::min(std::max(g.ry, -c.lim_y_neg), c.lim_y_pos);
  g.mx = g.rx >= -c.lim_x_neg && g.rx <= c.lim_x_pos;
  g.my = g.ry >= -c.lim_y_neg && g.ry <= c.lim_y_pos;
  g.tx = z * crx;
  g.ty = z * cry;
  const double J00 = c.fx / z, J02 = -c.fx * g.tx / (z * z), J11 = c.fy / z, J12 = -c.fy * g.ty / (z * z);
  for (int j = 0; j < 3; ++j) {
    g.T[j] = J00 * c.R[j] + J02 * c.R[6 + j];
    g.T[3 + j] = J11 * c.R[3 + j] + J12 * c.R[6 + j];
  }
  double q[4] = {double(quat[0]), double(quat[1]), double(quat[2]), double(quat[3])};
  g.qnorm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  const double qd = std::max(g.qnorm, kMinNorm);
  for (int i = 0; i < 4; ++i) g.qn[i] = q[i] / qd;
  const double w = g.qn[0], qx = g.qn[1], qy = g.qn[2], qz = g.qn[3];
  const double R[9] = {1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy),
                       2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx),
                       2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)};
  std::copy(R, R + 9, g.Rq);
  for (int j = 0; j < 3; ++j) g.s[j] = std::exp(double(log_scale[j]));
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

// SH basis (and, when grad is given, its derivatives d B_k / d (x, y, z)) at a unit direction.
void sh_basis(int64_t degree, const double* d, double* B, double (*dB)[3]) {
  const double x = d[0], y = d[1], z = d[2];
  B[0] = C0;
  if (dB) dB[0][0] = dB[0][1] = dB[0][2] = 0;
  if (degree >= 1) {
    B[1] = -C1 * y;
    B[2] = C1 * z;
    B[3] = -C1 * x;
    if (dB) {
      const double g[3][3] = {{0, -C1, 0}, {0, 0, C1}, {-C1, 0, 0}};
      for (int k = 0; k < 3; ++k) std::copy(g[k], g[k] + 3, dB[1 + k]);
    }
  }
  if (degree >= 2) {
    const double xx = x * x, yy = y * y, zz = z * z;
    B[4] = C2[0] * x * y;
    B[5] = C2[1] * y * z;
    B[6] = C2[2] * (2.0 * zz - xx - yy);
    B[7] = C2[3] * x * z;
    B[8] = C2[4] * (xx - yy);
    if (dB) {
      const double g[5][3] = {{C2[0] * y, C2[0] * x, 0},
                              {0, C2[1] * z, C2[1] * y},
                              {-2 * C2[2] * x, -2 * C2[2] * y, 4 * C2[2] * z},
                              {C2[3] * z, 0, C2[3] * x},
                              {2 * C2[4] * x, -2 * C2[4] * y, 0}};
      for (int k = 0; k < 5; ++k) std::copy(g[k], g[k] + 3, dB[4 + k]);
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
        const double g[7][3] = {{C3[0] * 6 * x * y, C3[0] * (3 * xx - 3 * yy), 0},
                                {C3[1] * y * z, C3[1] * x * z, C3[1] * x * y},
                                {C3[2] * -2 * x * y, C3[2] * (4 * zz - xx - 3 * yy), C3[2] * 8 * y * z},
                                {C3[3] * -6 * x * z, C3[3] * -6 * y * z, C3[3] * (6 * zz - 3 * xx - 3 * yy)},
                                {C3[4] * (4 * zz - 3 * xx - yy), C3[4] * -2 * x * y, C3[4] * 8 * x * z},
                                {C3[5] * 2 * x * z, C3[5] * -2 * y * z, C3[5] * (xx - yy)},
                                {C3[6] * (3 * xx - 3 * yy), C3[6] * -6 * x * y, 0}};
        for (int k = 0; k < 7; ++k) std::copy(g[k], g[k] + 3, dB[9 + k]);
      }
    }
  }
}

struct Params {
  int64_t N, n_rest_stored;
};

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
    at::parallel_for(0, N, 8192, [&](int64_t b, int64_t e) {
      Geo g;
      double B[16];
      for (int64_t i = b; i < e; ++i) {
        for (int j = 0; j < 2; ++j) om[2 * i + j] = 0;
        for (int j = 0; j < 3; ++j) oc[3 * i + j] = ocol[3 * i + j] = 0;
        oo[i] = oz[i] = 0;
        orad[i] = 0;
        const double z0 = c.R[6] * double(pm[3 * i]) + c.R[7] * double(pm[3 * i + 1]) +
                          c.R[8] * double(pm[3 * i + 2]) + c.t[2];
        if (!(z0 > c.near && z0 < c.far)) continue;
        geometry(c, pm + 3 * i, pq + 4 * i, ps + 3 * i, g);
        om[2 * i] = static_cast<S>(g.u);
        om[2 * i + 1] = static_cast<S>(g.v);
        oz[i] = static_cast<S>(g.p[2]);
        oc[3 * i] = static_cast<S>(g.cyy / g.det);
        oc[3 * i + 1] = static_cast<S>(-g.cxy / g.det);
        oc[3 * i + 2] = static_cast<S>(g.cxx / g.det);
        const double mid = 0.5 * (g.cxx + g.cyy);
        const double lam = mid + std::sqrt(std::max(mid * mid - g.det, 0.0));
        double r = std::ceil(c.radius_sigmas * std::sqrt(lam));
        const bool on = (g.u + r > 0) && (g.u - r < c.width) && (g.v + r > 0) && (g.v - r < c.height);
        if (!on || !std::isfinite(r)) r = 0;
        r = std::min(r, kMaxRadius);
        orad[i] = static_cast<int32_t>(r);
        if (orad[i] <= 0) continue;
        oo[i] = static_cast<S>(1.0 / (1.0 + std::exp(-double(pl[i]))));
        double dir[3] = {0, 0, 0};
        if (degree > 0) {
          double d[3], n2 = 0;
          for (int j = 0; j < 3; ++j) {
            d[j] = double(pm[3 * i + j]) - c.campos[j];
            n2 += d[j] * d[j];
          }
          const double nd = std::max(std::sqrt(n2), kMinNorm);
          for (int j = 0; j < 3; ++j) dir[j] = d[j] / nd;
        }
        sh_basis(degree, dir, B, nullptr);
        for (int ch = 0; ch < 3; ++ch) {
          double acc = B[0] * double(pdc[3 * i + ch]);
          for (int64_t k = 1; k < nb; ++k) acc += B[k] * double(prest[(i * KR + k - 1) * 3 + ch]);
          ocol[3 * i + ch] = static_cast<S>(std::max(acc + 0.5, 0.0));
        }
      }
    });
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
  at::Tensor gl = at::empty({N}, opts), gdc = at::empty({N, 1, 3}, opts), grest = at::zeros({N, KR, 3}, opts);
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
    at::parallel_for(0, N, 8192, [&](int64_t b, int64_t e) {
      Geo g;
      double B[16], dB[16][3];
      for (int64_t i = b; i < e; ++i) {
        const S wi = scaled ? sc[i] : S(1);  // x * 1 is x: the unscaled bits when there is no factor
        for (int j = 0; j < 3; ++j) om[3 * i + j] = os[3 * i + j] = odc[3 * i + j] = 0;
        for (int j = 0; j < 4; ++j) oq[4 * i + j] = 0;
        ol[i] = 0;
        const double z0 = c.R[6] * double(pm[3 * i]) + c.R[7] * double(pm[3 * i + 1]) +
                          c.R[8] * double(pm[3 * i + 2]) + c.t[2];
        if (!(z0 > c.near && z0 < c.far)) continue;
        geometry(c, pm + 3 * i, pq + 4 * i, ps + 3 * i, g);
        double gmean[3] = {0, 0, 0};
        // Colour and opacity (visible Gaussians only).
        if (rad[i] > 0) {
          const double o = 1.0 / (1.0 + std::exp(-double(pl[i])));
          ol[i] = static_cast<S>(double(uo[i]) * o * (1 - o)) * wi;
          double dir[3] = {0, 0, 0}, d[3] = {0, 0, 0}, nd = 1;
          if (degree > 0) {
            double n2 = 0;
            for (int j = 0; j < 3; ++j) {
              d[j] = double(pm[3 * i + j]) - c.campos[j];
              n2 += d[j] * d[j];
            }
            nd = std::max(std::sqrt(n2), kMinNorm);
            for (int j = 0; j < 3; ++j) dir[j] = d[j] / nd;
          }
          sh_basis(degree, dir, B, dB);
          double gdir[3] = {0, 0, 0};
          for (int ch = 0; ch < 3; ++ch) {
            double acc = B[0] * double(pdc[3 * i + ch]);
            for (int64_t k = 1; k < nb; ++k) acc += B[k] * double(prest[(i * KR + k - 1) * 3 + ch]);
            // clamp_min passes the gradient where the input is >= the bound.
            const double gc = acc + 0.5 >= 0.0 ? double(ucol[3 * i + ch]) : 0.0;
            odc[3 * i + ch] = static_cast<S>(B[0] * gc) * wi;
            for (int64_t k = 1; k < nb; ++k) {
              orest[(i * KR + k - 1) * 3 + ch] = static_cast<S>(B[k] * gc) * wi;
              const double cf = double(prest[(i * KR + k - 1) * 3 + ch]) * gc;
              for (int j = 0; j < 3; ++j) gdir[j] += cf * dB[k][j];
            }
          }
          if (degree > 0) {
            // d (d / |d|) = (I - dir dir^T) / |d|; with the norm clamped the Jacobian is I / 1e-12.
            const double dot = dir[0] * gdir[0] + dir[1] * gdir[1] + dir[2] * gdir[2];
            const bool clamped = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) < kMinNorm;
            for (int j = 0; j < 3; ++j) gmean[j] += clamped ? gdir[j] / nd : (gdir[j] - dir[j] * dot) / nd;
          }
        }
        // Conic = inverse of the dilated covariance.
        const double ga = uc[3 * i], gb = uc[3 * i + 1], gcc = uc[3 * i + 2];
        const double det = g.det, d2 = det * det, cxx = g.cxx, cxy = g.cxy, cyy = g.cyy;
        const double g_cxx = ga * (-cyy * cyy / d2) + gb * (cxy * cyy / d2) + gcc * (1.0 / det - cxx * cyy / d2);
        const double g_cyy = ga * (1.0 / det - cyy * cxx / d2) + gb * (cxy * cxx / d2) + gcc * (-cxx * cxx / d2);
        const double g_cxy = ga * (2 * cyy * cxy / d2) + gb * (-1.0 / det - 2 * cxy * cxy / d2) +
                             gcc * (2 * cxx * cxy / d2);
        // cov = V V^T.
        double gV[6];
        for (int j = 0; j < 3; ++j) {
          gV[j] = 2 * g_cxx * g.V[j] + g_cxy * g.V[3 + j];
          gV[3 + j] = 2 * g_cyy * g.V[3 + j] + g_cxy * g.V[j];
        }
        // V = T Rq diag(s): gT = gV (Rq diag(s))^T, gM = T^T gV with M = Rq diag(s).
        double gT[6] = {0, 0, 0, 0, 0, 0}, gRq[9], glog[3];
        for (int r = 0; r < 2; ++r)
          for (int k = 0; k < 3; ++k)
            for (int j = 0; j < 3; ++j) gT[3 * r + k] += gV[3 * r + j] * g.Rq[3 * k + j] * g.s[j];
        for (int j = 0; j < 3; ++j) {
          double gsj = 0;
          for (int k = 0; k < 3; ++k) {
            const double gM = g.T[k] * gV[j] + g.T[3 + k] * gV[3 + j];
            gRq[3 * k + j] = gM * g.s[j];
            gsj += gM * g.Rq[3 * k + j];
          }
          glog[j] = gsj * g.s[j];
        }
        // T = J R: gJ = gT R^T (entries 00, 02, 11, 12 are the non-constant ones).
        auto gJ = [&](int r, int k) {
          return gT[3 * r] * c.R[3 * k] + gT[3 * r + 1] * c.R[3 * k + 1] + gT[3 * r + 2] * c.R[3 * k + 2];
        };
        const double gJ00 = gJ(0, 0), gJ02 = gJ(0, 2), gJ11 = gJ(1, 1), gJ12 = gJ(1, 2);
        const double x = g.p[0], y = g.p[1], z = g.p[2], z2 = z * z, z3 = z2 * z;
        double gx = 0, gy = 0, gz = double(uz[i]);
        gz += gJ00 * (-c.fx / z2) + gJ11 * (-c.fy / z2) + gJ02 * (2 * c.fx * g.tx / z3) +
              gJ12 * (2 * c.fy * g.ty / z3);
        const double gtx = gJ02 * (-c.fx / z2), gty = gJ12 * (-c.fy / z2);
        // tx = z clamp(x / z): d/dx = [unclamped], d/dz = clamp(x / z) - [unclamped] x / z.
        gx += g.mx ? gtx : 0.0;
        gz += gtx * (g.tx / z - (g.mx ? g.rx : 0.0));
        gy += g.my ? gty : 0.0;
        gz += gty * (g.ty / z - (g.my ? g.ry : 0.0));
        // Screen centre.
        const double gu = um[2 * i], gv = um[2 * i + 1];
        gx += gu * c.fx / z;
        gy += gv * c.fy / z;
        gz += -gu * c.fx * x / z2 - gv * c.fy * y / z2;
        for (int j = 0; j < 3; ++j) gmean[j] += c.R[j] * gx + c.R[3 + j] * gy + c.R[6 + j] * gz;
        for (int j = 0; j < 3; ++j) om[3 * i + j] = static_cast<S>(gmean[j]) * wi;
        for (int j = 0; j < 3; ++j) os[3 * i + j] = static_cast<S>(glog[j]) * wi;
        // Rotation of the normalised quaternion.
        const double w = g.qn[0], qx = g.qn[1], qy = g.qn[2], qz = g.qn[3];
        const double* G = gRq;
        double gqn[4];
        gqn[0] = 2 * (-qz * G[1] + qy * G[2] + qz * G[3] - qx * G[5] - qy * G[6] + qx * G[7]);
        gqn[1] = 2 * (qy * G[1] + qz * G[2] + qy * G[3] - 2 * qx * G[4] - w * G[5] + qz * G[6] + w * G[7] -
                      2 * qx * G[8]);
        gqn[2] = 2 * (-2 * qy * G[0] + qx * G[1] + w * G[2] + qx * G[3] + qz * G[5] - w * G[6] + qz * G[7] -
                      2 * qy * G[8]);
        gqn[3] = 2 * (-2 * qz * G[0] - w * G[1] + qx * G[2] + w * G[3] - 2 * qz * G[4] + qy * G[5] + qx * G[6] +
                      qy * G[7]);
        if (g.qnorm > kMinNorm) {
          const double dot = gqn[0] * g.qn[0] + gqn[1] * g.qn[1] + gqn[2] * g.qn[2] + gqn[3] * g.qn[3];
          for (int j = 0; j < 4; ++j) oq[4 * i + j] = static_cast<S>((gqn[j] - g.qn[j] * dot) / g.qnorm) * wi;
        } else {
          for (int j = 0; j < 4; ++j) oq[4 * i + j] = static_cast<S>(gqn[j] / kMinNorm) * wi;
        }
      }
    });
  });
  return {gm, gq, gs, gl, gdc, grest};
}

// Tile-sorted intersection lists (binning.py's contract) for Gaussians with radius > 0.
// Counting sort by tile of the Gaussians taken in depth order: O(N log N + I), no sort
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
    std::stable_sort(order.begin(), order.end(), [&](int64_t a, int64_t b) { return z[a] < z[b]; });
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
