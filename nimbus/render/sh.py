"""Real spherical harmonics (degree 0..3) for view-dependent Gaussian colour.

The basis, its sign convention and the constants are those of the 3DGS reference
implementation (and gsplat), so SH coefficients trained elsewhere render the same
here.  A colour is ``max(SH(dir) + 0.5, 0)``; the DC coefficient of a constant RGB
colour ``c`` is therefore ``(c - 0.5) / C0`` (:func:`rgb_to_sh`).
"""

from __future__ import annotations

import torch
from torch import Tensor

C0 = 0.28209479177387814
"""Degree-0 basis constant, 1 / (2 sqrt(pi))."""
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)
MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per colour channel for ``degree`` (1, 4, 9 or 16)."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    return (degree + 1) ** 2


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """DC coefficient that renders as the constant colour ``rgb`` (any shape, values in [0, 1])."""
    return (rgb - 0.5) / C0


def sh_to_rgb(dc: Tensor) -> Tensor:
    """Colour of a DC-only SH coefficient (inverse of :func:`rgb_to_sh`, before the clamp at 0)."""
    return dc * C0 + 0.5


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Real SH basis functions of ``degree`` at unit directions.

    Parameters
    ----------
    degree : int
        0..3.
    dirs : Tensor, shape [N, 3]
        Unit directions.

    Returns
    -------
    Tensor, shape [N, (degree + 1)**2]
    """
    k = num_sh_bases(degree)
    x, y, z = dirs.unbind(-1)
    terms = [torch.full_like(x, C0)]
    if degree >= 1:
        terms += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        terms += [
            C2[0] * xy,
            C2[1] * yz,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * xz,
            C2[4] * (xx - yy),
        ]
    if degree >= 3:
        terms += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    assert len(terms) == k
    return torch.stack(terms, dim=-1)


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate real SH of ``degree`` for every Gaussian.

    Parameters
    ----------
    degree : int
        Active degree, 0..3; only the first ``(degree + 1)**2`` coefficients are used.
    coeffs : Tensor, shape [N, K, 3]
        SH coefficients, ``K >= (degree + 1)**2``.
    dirs : Tensor, shape [N, 3]
        Unit viewing directions (camera centre to Gaussian, world frame).

    Returns
    -------
    Tensor, shape [N, 3]
        ``SH(dir)`` per channel, *without* the +0.5 offset and clamp (see :func:`sh_colors`).
    """
    k = num_sh_bases(degree)
    if coeffs.shape[-2] < k:
        raise ValueError(f"degree {degree} needs {k} SH coefficients, got {coeffs.shape[-2]}")
    # One batched product: its backward is one op, where per-coefficient slicing would
    # allocate a zero-filled copy of all coefficients for every band.
    return torch.bmm(sh_basis(degree, dirs)[:, None, :], coeffs[:, :k]).squeeze(1)


def sh_colors(degree: int, coeffs: Tensor, means: Tensor, camera_center: Tensor) -> Tensor:
    """RGB colour of each Gaussian seen from ``camera_center``: ``max(SH(dir) + 0.5, 0)``.

    Parameters
    ----------
    degree : int
        Active SH degree, 0..3.
    coeffs : Tensor, shape [N, K, 3]
    means : Tensor, shape [N, 3]
        Gaussian centres, world frame.
    camera_center : Tensor, shape [3]

    Returns
    -------
    Tensor, shape [N, 3], values >= 0 (not clamped above: SH colours may exceed 1).
    """
    if degree == 0:
        # Direction-free; skips a normalisation whose gradient would be wasted work.
        return torch.clamp_min(C0 * coeffs[:, 0] + 0.5, 0.0)
    d = means - camera_center
    # The clamp keeps a Gaussian sitting exactly on the camera centre finite (its
    # direction is undefined; such a Gaussian is culled by the near plane anyway).
    dirs = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.clamp_min(eval_sh(degree, coeffs, dirs) + 0.5, 0.0)
