"""Tile binning: which Gaussians touch which screen tiles, sorted front to back.

Fully vectorised (no Python loop over Gaussians or tiles): each Gaussian covers the
rectangle of tiles overlapped by its square ``[mean - radius, mean + radius]``; the
(Gaussian, tile) pairs are expanded with ``repeat_interleave``, ordered by one sort on
the combined key ``tile * M + depth_rank`` and cut into per-tile ranges with
``searchsorted``.  Depth ties are broken by Gaussian index (stable rank), which the
dense reference reproduces.
"""

from __future__ import annotations

import torch
from torch import Tensor


def tile_grid(width: int, height: int, tile_size: int) -> tuple[int, int]:
    """Number of tiles (tiles_x, tiles_y) covering a ``width`` x ``height`` image."""
    return -(-width // tile_size), -(-height // tile_size)


def tile_rects(means2d: Tensor, radii: Tensor, width: int, height: int, tile_size: int) -> Tensor:
    """Tile rectangle [x0, y0, x1, y1) of each Gaussian, clipped to the grid; [M, 4] int64.

    Empty (x1 <= x0 or y1 <= y0) for a Gaussian with radius 0 or one off the grid.
    """
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    r = radii.to(means2d.dtype)[:, None]
    lo = torch.floor((means2d - r) / tile_size)
    hi = torch.ceil((means2d + r) / tile_size)
    lim = torch.tensor([tiles_x, tiles_y], dtype=means2d.dtype, device=means2d.device)
    lo = torch.minimum(torch.clamp_min(lo, 0), lim).to(torch.int64)
    hi = torch.minimum(torch.clamp_min(hi, 0), lim).to(torch.int64)
    rect = torch.cat([lo, hi], dim=1)
    rect[radii <= 0] = 0
    return rect


@torch.no_grad()
def bin_gaussians(
    means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int, tile_size: int
) -> tuple[Tensor, Tensor]:
    """Tile/depth-sorted intersection lists for M Gaussians.

    Parameters
    ----------
    means2d : Tensor [M, 2]   pixel coordinates (pixel-corner origin).
    radii : Tensor [M]        screen radii in pixels; <= 0 means not drawn.
    depths : Tensor [M]       camera z (sort key within a tile, ascending = front to back).
    width, height, tile_size : int

    Returns
    -------
    isect_ids : Tensor [I] int64
        Gaussian indices, grouped by tile (row-major) and front to back within a tile.
    tile_offsets : Tensor [T + 1] int64
        Tile ``t`` owns ``isect_ids[tile_offsets[t]:tile_offsets[t + 1]]``.
    """
    device = means2d.device
    m = means2d.shape[0]
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    n_tiles = tiles_x * tiles_y
    rect = tile_rects(means2d.detach(), radii, width, height, tile_size)
    w = (rect[:, 2] - rect[:, 0]).clamp_min(0)
    h = (rect[:, 3] - rect[:, 1]).clamp_min(0)
    counts = w * h
    total = int(counts.sum())
    if total == 0:
        return (torch.zeros(0, dtype=torch.int64, device=device),
                torch.zeros(n_tiles + 1, dtype=torch.int64, device=device))

    gauss = torch.repeat_interleave(torch.arange(m, device=device), counts, output_size=total)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(total, device=device) - first[gauss]
    gw = w[gauss]
    tile = (rect[gauss, 1] + local // gw) * tiles_x + rect[gauss, 0] + local % gw

    depth_rank = torch.empty(m, dtype=torch.int64, device=device)
    depth_rank[torch.sort(depths.detach(), stable=True).indices] = torch.arange(m, device=device)
    key = tile * m + depth_rank[gauss]
    key, order = torch.sort(key)
    isect_ids = gauss[order]
    sorted_tiles = key // m
    tile_offsets = torch.searchsorted(sorted_tiles, torch.arange(n_tiles + 1, device=device))
    return isect_ids, tile_offsets
