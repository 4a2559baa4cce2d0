"""The "torch" backend: the reference pipeline in plain torch ops, on any device.

EWA projection with near/frustum culling (:mod:`~nimbus.render.projection`), SH colour of
the visible Gaussians (:mod:`~nimbus.render.sh`), tile binning (:mod:`~nimbus.render.binning`)
and per-tile front-to-back compositing (:mod:`~nimbus.render.composite_torch`).  The
visible Gaussians are gathered first; ``meta["means2d"]`` is the [N, 2] tensor they were
gathered from, so its gradient is zero for culled Gaussians.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from nimbus.render.backends.base import Backend, make_meta
from nimbus.render.binning import bin_gaussians
from nimbus.render.composite_torch import composite
from nimbus.render.gaussians import Gaussians
from nimbus.render.projection import ProjectionConfig, project_gaussians
from nimbus.render.sh import sh_colors


@dataclass
class Shaded:
    """Projected, culled and coloured Gaussians: what a compositor needs.

    ``means2d``, ``radii`` and ``depths`` are per Gaussian ([N, ...], zeros where culled);
    the ``vis_*`` tensors hold the M visible ones, in the order of ``visible_ids``.
    """

    means2d: Tensor      # [N, 2], the tensor whose .grad feeds densification
    radii: Tensor        # [N] int32
    depths: Tensor       # [N]
    visible_ids: Tensor  # [M] int64
    vis_means2d: Tensor  # [M, 2]
    vis_conics: Tensor   # [M, 3]
    vis_colors: Tensor   # [M, 3]
    vis_opacities: Tensor  # [M]
    vis_depths: Tensor   # [M]
    vis_radii: Tensor    # [M]


def project_and_shade(
    gaussians: Gaussians,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    sh_degree: int,
    config: ProjectionConfig,
) -> Shaded:
    """Project all Gaussians, keep the visible ones and evaluate their SH colour and opacity."""
    proj = project_gaussians(gaussians.means, gaussians.quats, gaussians.log_scales, viewmat, K, width, height,
                             config)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    vis = torch.nonzero(proj.radii > 0).squeeze(1)
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    center = -(R.T @ t)
    n_rest = (sh_degree + 1) ** 2 - 1  # only the active bands are gathered (and get gradients)
    sh = torch.cat([gaussians.sh_dc[vis], gaussians.sh_rest[vis, :n_rest]], dim=1) if n_rest else gaussians.sh_dc[vis]
    colors = sh_colors(sh_degree, sh, gaussians.means[vis], center)
    return Shaded(
        means2d=means2d, radii=proj.radii, depths=proj.depths, visible_ids=vis,
        vis_means2d=means2d[vis], vis_conics=proj.conics[vis], vis_colors=colors,
        vis_opacities=torch.sigmoid(gaussians.opacity_logits[vis]), vis_depths=proj.depths[vis],
        vis_radii=proj.radii[vis],
    )


def project_and_bin(gaussians: Gaussians, viewmat, K, width, height, sh_degree, config):
    """:func:`project_and_shade`, then tile binning of the visible Gaussians.

    Returns
    -------
    shaded : Shaded
    args : tuple
        The positional arguments of :func:`nimbus.render.composite_torch.composite` (and of
        the compiled compositor, which shares its signature) for these Gaussians.
    """
    s = project_and_shade(gaussians, viewmat, K, width, height, sh_degree, config.projection)
    isect_ids, tile_offsets = bin_gaussians(s.vis_means2d, s.vis_radii, s.vis_depths, width, height,
                                            config.tile_size)
    return s, (s.vis_means2d, s.vis_conics, s.vis_colors, s.vis_opacities, s.vis_depths, isect_ids, tile_offsets,
               width, height, config.tile_size)


def rasterize(gaussians: Gaussians, viewmat, K, width, height, sh_degree, background, config, absgrad):
    """The :class:`~nimbus.render.backends.base.Backend` call of this backend (see there)."""
    s, args = project_and_bin(gaussians, viewmat, K, width, height, sh_degree, config)
    rgb, depth, alpha = composite(*args, background, config=config.composite)
    return rgb, depth, alpha, make_meta(s.means2d, s.radii, s.depths, args[5].numel(), "torch", width, height)


BACKEND = Backend(name="torch", rasterize=rasterize, available=lambda device: True, auto_rank=0)
