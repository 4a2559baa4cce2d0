"""EWA projection of 3D Gaussians to screen-space ellipses.

Camera conventions are those of :mod:`nimbus.data.camera`: OpenCV camera frame,
world-to-camera ``viewmat``, pixel-corner origin (pixel (u, v) has its centre at
(u + 0.5, v + 0.5)), so a camera-frame point (x, y, z) lands at
``(fx x / z + cx, fy y / z + cy)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class ProjectionConfig:
    """Constants of the projection (defaults follow gsplat).

    Attributes
    ----------
    near, far : float
        Gaussians whose camera z is <= ``near`` or >= ``far`` are culled (camera units).
    eps2d : float
        Added to the diagonal of the 2D covariance (pixels^2): the low-pass filter that
        keeps every splat at least about one pixel wide.
    fov_clamp : float
        The Jacobian is evaluated at x/z, y/z clamped to this many times the half-FoV
        tangent, so Gaussians far outside the view do not get huge, unstable footprints.
    radius_sigmas : float
        Screen radius in standard deviations of the largest 2D axis.
    """

    near: float = 0.01
    far: float = 1e10
    eps2d: float = 0.3
    fov_clamp: float = 1.3
    radius_sigmas: float = 3.0


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities for N Gaussians (zeros where culled).

    Attributes
    ----------
    means2d : Tensor [N, 2]   pixel coordinates (pixel-corner origin).
    conics : Tensor [N, 3]    (a, b, c) of the inverse 2D covariance [[a, b], [b, c]].
    depths : Tensor [N]       camera z.
    radii : Tensor [N] int32  screen radius in pixels, 0 when culled.
    cov2d : Tensor [N, 3]     (xx, xy, yy) of the dilated 2D covariance.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    cov2d: Tensor

    @property
    def visible(self) -> Tensor:
        return self.radii > 0


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [N, 3, 3] from (w, x, y, z) quaternions [N, 4] (normalised here)."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


def covariance_3d(quats: Tensor, log_scales: Tensor) -> Tensor:
    """World covariances ``R S S^T R^T`` [N, 3, 3] from quaternions [N, 4] and log-scales [N, 3]."""
    M = quat_to_rotmat(quats) * torch.exp(log_scales)[:, None, :]  # R @ diag(s)
    return M @ M.transpose(1, 2)


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    config: ProjectionConfig = ProjectionConfig(),
) -> Projected:
    """Project N Gaussians with the EWA approximation.

    Parameters
    ----------
    means : Tensor [N, 3]        world centres.
    quats : Tensor [N, 4]        (w, x, y, z), need not be normalised.
    log_scales : Tensor [N, 3]   log standard deviations.
    viewmat : Tensor [4, 4]      world-to-camera (OpenCV axes).
    K : Tensor [3, 3]            intrinsics in pixels.
    width, height : int          image size in pixels.
    config : ProjectionConfig

    Returns
    -------
    Projected
        Only the Gaussians in front of the near plane are put through the maths, and the
        results are scattered into zero-filled [N, ...] tensors: masking after the maths
        would let the NaN/inf of culled Gaussians leak into the gradients. A Gaussian is
        visible (radius > 0) when it lies between the near and far planes and its
        radius box overlaps the image.
    """
    n = means.shape[0]
    dtype, device = means.dtype, means.device
    R, t = viewmat[:3, :3].to(dtype), viewmat[:3, 3].to(dtype)
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))

    with torch.no_grad():
        z_all = means @ R[2] + t[2]
        in_depth = (z_all > config.near) & (z_all < config.far)
        idx = torch.nonzero(in_depth).squeeze(1)

    p = means[idx] @ R.T + t
    x, y, z = p.unbind(-1)
    u = fx * x / z + cx
    v = fy * y / z + cy

    # gsplat's form of the FoV clamp: equals 1.3 * tan(fov/2) for a centred principal point.
    lim_x_pos = (width - cx) / fx + (config.fov_clamp - 1) * 0.5 * width / fx
    lim_x_neg = cx / fx + (config.fov_clamp - 1) * 0.5 * width / fx
    lim_y_pos = (height - cy) / fy + (config.fov_clamp - 1) * 0.5 * height / fy
    lim_y_neg = cy / fy + (config.fov_clamp - 1) * 0.5 * height / fy
    tx = z * torch.clamp(x / z, -lim_x_neg, lim_x_pos)
    ty = z * torch.clamp(y / z, -lim_y_neg, lim_y_pos)
    zero = torch.zeros_like(z)
    J = torch.stack(
        [fx / z, zero, -fx * tx / (z * z), zero, fy / z, -fy * ty / (z * z)], dim=-1
    ).reshape(-1, 2, 3)
    # Sigma_2d = J W Sigma W^T J^T with W = R; T = J R folds the rotation into the Jacobian.
    M = quat_to_rotmat(quats[idx]) * torch.exp(log_scales[idx])[:, None, :]
    TM = (J @ R) @ M
    cov = TM @ TM.transpose(1, 2)
    cxx = cov[:, 0, 0] + config.eps2d
    cxy = cov[:, 0, 1]
    cyy = cov[:, 1, 1] + config.eps2d
    det = cxx * cyy - cxy * cxy  # >= eps2d^2 > 0: the covariance is PSD before the dilation
    conic = torch.stack([cyy / det, -cxy / det, cxx / det], dim=-1)

    with torch.no_grad():
        mid = 0.5 * (cxx + cyy)
        lam_max = mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.0))
        radius = torch.ceil(config.radius_sigmas * torch.sqrt(lam_max))
        on_screen = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
        radius = torch.where(on_screen & torch.isfinite(radius), radius, torch.zeros_like(radius))
        radius = radius.clamp_max(2.0**30)  # int32-safe: a splat grazing the near plane must not wrap to <= 0
        radii = torch.zeros(n, dtype=torch.int32, device=device)
        radii[idx] = radius.to(torch.int32)

    def scatter(values: Tensor) -> Tensor:
        out = torch.zeros((n,) + values.shape[1:], dtype=values.dtype, device=device)
        return out.index_put((idx,), values)

    return Projected(
        means2d=scatter(torch.stack([u, v], dim=-1)),
        conics=scatter(conic),
        depths=scatter(z),
        radii=radii,
        cov2d=scatter(torch.stack([cxx, cxy, cyy], dim=-1)),
    )
