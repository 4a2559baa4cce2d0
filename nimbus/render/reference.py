"""A naive, obviously-correct dense compositor: the yardstick of the fast paths.

Every pixel is tested against every Gaussian, walking the Gaussians in global depth
order (ties by index) with the rules of :mod:`nimbus.render.composite_torch`; plain
autograd gives the gradients.  Slow (a Python loop over Gaussians): for tests and
the benchmark's small size only.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from nimbus.render.composite_torch import ALPHA_MAX, ALPHA_MIN, T_STOP


def composite_dense(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    depths: Tensor,
    radii: Tensor | None,
    width: int,
    height: int,
    tile_size: int,
    background: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """Dense reference of :func:`nimbus.render.composite_torch.composite`.

    Parameters
    ----------
    means2d, conics, colors, opacities, depths
        As in the tiled ``composite``, for M Gaussians.
    radii : Tensor [M] or None
        Screen radii.  When given, a Gaussian only reaches the pixels of the tiles its
        radius box overlaps (as binning does: beyond 3 sigma an opaque Gaussian still has
        alpha >= 1/255, so the box matters); radius <= 0 draws nothing.  None: no box.
    width, height, tile_size : int
    background : Tensor [3]

    Returns
    -------
    rgb [H, W, 3], depth [H, W] (not normalised), alpha [H, W].
    """
    dtype, device = means2d.dtype, means2d.device
    ys, xs = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij")
    tx, ty = (xs // tile_size).reshape(-1), (ys // tile_size).reshape(-1)
    px = xs.reshape(-1).to(dtype) + 0.5
    py = ys.reshape(-1).to(dtype) + 0.5
    n_pix = width * height
    T = torch.ones(n_pix, dtype=dtype, device=device)
    done = torch.zeros(n_pix, dtype=torch.bool, device=device)
    rgb = torch.zeros(n_pix, 3, dtype=dtype, device=device)
    depth = torch.zeros(n_pix, dtype=dtype, device=device)
    order = torch.sort(depths.detach(), stable=True).indices.tolist()
    for i in order:
        if radii is not None:
            r = float(radii[i])
            if r <= 0:
                continue
            mx, my = (float(v) for v in means2d[i].detach())
            covered = ((tx >= math.floor((mx - r) / tile_size)) & (tx < math.ceil((mx + r) / tile_size))
                       & (ty >= math.floor((my - r) / tile_size)) & (ty < math.ceil((my + r) / tile_size)))
        else:
            covered = torch.ones(n_pix, dtype=torch.bool, device=device)
        dx = px - means2d[i, 0]
        dy = py - means2d[i, 1]
        sigma = 0.5 * (conics[i, 0] * dx * dx + conics[i, 2] * dy * dy) + conics[i, 1] * dx * dy
        alpha = torch.clamp_max(opacities[i] * torch.exp(-sigma), ALPHA_MAX)
        drawn = covered & ~done & (sigma >= 0) & (alpha >= ALPHA_MIN)
        T_next = T * (1 - alpha)
        stop = drawn & (T_next < T_STOP)
        done = done | stop
        use = drawn & ~stop
        w = torch.where(use, alpha * T, torch.zeros_like(T))
        rgb = rgb + w[:, None] * colors[i]
        depth = depth + w * depths[i]
        T = torch.where(use, T_next, T)
    rgb = rgb + T[:, None] * background.to(dtype)
    return rgb.reshape(height, width, 3), depth.reshape(height, width), (1 - T).reshape(height, width)


def rasterize_reference(
    gaussians,
    camera=None,
    *,
    viewmat: Tensor | None = None,
    K: Tensor | None = None,
    width: int | None = None,
    height: int | None = None,
    sh_degree: int | None = None,
    background=None,
    config=None,
    respect_tiles: bool = True,
) -> tuple[Tensor, Tensor, Tensor, dict]:
    """:func:`nimbus.render.rasterize.rasterize` with the dense compositor instead of tiles.

    Projection and SH colour are shared with the fast path; binning and compositing are
    replaced by :func:`composite_dense` (``respect_tiles`` as its ``radii`` argument).
    Returns the same ``(rgb, depth, alpha, meta)``; meta has ``means2d``, ``radii``,
    ``depths`` and ``visible``.
    """
    from nimbus.render.backends.torch import project_and_shade
    from nimbus.render.rasterize import RasterConfig, resolve_camera

    cfg = config or RasterConfig()
    viewmat, K, width, height = resolve_camera(gaussians, camera, viewmat, K, width, height)
    dtype, device = gaussians.means.dtype, gaussians.device
    deg = gaussians.sh_degree if sh_degree is None else sh_degree
    bg = torch.zeros(3, dtype=dtype, device=device) if background is None else \
        torch.as_tensor(background).to(dtype=dtype, device=device).reshape(3)
    s = project_and_shade(gaussians, viewmat, K, width, height, deg, cfg.projection)
    rgb, depth, alpha = composite_dense(s.vis_means2d, s.vis_conics, s.vis_colors, s.vis_opacities, s.vis_depths,
                                        s.vis_radii if respect_tiles else None, width, height, cfg.tile_size, bg)
    meta = {"means2d": s.means2d, "radii": s.radii, "depths": s.depths, "visible": s.radii > 0}
    return rgb, depth, alpha, meta
