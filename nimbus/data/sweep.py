"""Depths of chosen pixels from the photos themselves: a plane sweep over a view's posed neighbours.

SIFT on small photos triangulates points on the most textured surfaces only; the backdrop (far hills,
clouds, the end of a street) gets none, and :mod:`nimbus.data.densify` used to put its pixels at a guessed
far depth.  With the poses known, a pixel's depth can be measured instead: :func:`sweep_depths` tries
``steps`` depths, uniform in inverse depth between ``near`` and ``far``, and for each one projects a small
patch about the pixel (fronto-parallel to the view) into the ``neighbours`` nearest training views and
compares colours there by zero-mean normalised cross-correlation (ZNCC, which forgives the brightness and
contrast changes a haze that differs from view to view makes).  The cost of a depth is the mean of the
better half of the neighbours' ``1 - ZNCC`` (an occluded or rain-streaked neighbour does not spoil it).

A depth is kept only where it is measured: the patch has texture (its standard deviation at least
``min_std``), at least two neighbours see it, the best cost is below ``max_cost``, and no depth farther
than ``exclusion`` steps from the best comes within ``margin`` of its cost (a flat or repeating cost curve
is a guess).  Everything else comes back NaN, and the caller keeps its own fallback.  This is the classic
plane-sweep stereo of Collins (1996) in its simplest form, no regularisation across pixels: it only has
to seed Gaussians that training then moves.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from nimbus.data.camera import Camera
from nimbus.errors import NimbusError


@dataclass(frozen=True)
class SweepConfig:
    """Settings of :func:`sweep_depths`.

    Attributes
    ----------
    steps : int
        Depths tried, uniform in inverse depth (default 64).
    neighbours : int
        Nearest other views (by camera centre) the patch is compared in (default 4).
    max_axis_angle : float
        Degrees: a neighbour's optical axis must be within this of the view's (default 60).
    patch : int
        Patch radius in pixels (default 2: 5 x 5).
    min_std : float
        Least standard deviation of the reference patch (image values in [0, 1]; default 0.02).
    max_cost : float
        Largest accepted ``1 - ZNCC`` at the best depth (default 0.3).
    margin : float
        The best cost must beat every depth more than ``exclusion`` steps from it by this much (default 0.1).
    exclusion : int
        Steps about the best depth exempt from the margin test (default 3).
    """

    steps: int = 64
    neighbours: int = 4
    max_axis_angle: float = 60.0
    patch: int = 2
    min_std: float = 0.02
    max_cost: float = 0.3
    margin: float = 0.1
    exclusion: int = 3

    def __post_init__(self) -> None:
        if self.steps < 2 or self.neighbours < 2 or self.patch < 1 or self.exclusion < 0:
            raise NimbusError("sweep steps and neighbours must be >= 2, patch >= 1 and exclusion >= 0")
        if not (0 < self.max_axis_angle <= 180 and self.min_std >= 0 and 0 < self.max_cost <= 2
                and self.margin >= 0):
            raise NimbusError("sweep max_axis_angle must be in (0, 180], min_std >= 0, max_cost in (0, 2] "
                              "and margin >= 0")


def neighbour_views(cameras: Sequence[Camera], index: int, count: int, max_axis_angle: float) -> list[int]:
    """Indices of up to ``count`` cameras nearest camera ``index`` (by centre) whose optical axes are within
    ``max_axis_angle`` degrees of its own, and that are not at the same place."""
    ref = cameras[index]
    axis = ref.R[2]
    cos_limit = np.cos(np.radians(max_axis_angle))
    order = []
    for j, cam in enumerate(cameras):
        if j == index:
            continue
        dist = float(np.linalg.norm(cam.center - ref.center))
        if dist <= 1e-9 or float(cam.R[2] @ axis) < cos_limit:
            continue
        order.append((dist, j))
    return [j for _, j in sorted(order)[:count]]


def _sample(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear colours (..., 3) of ``image`` at Nimbus pixel positions ``uv`` (..., 2) (pixel centres at +0.5)."""
    shape = uv.shape[:-1]
    flat = uv.reshape(-1, 2).astype(np.float32) - np.float32(0.5)
    # cv2.remap takes maps of fewer than 32767 rows and columns.
    rows = [cv2.remap(image, flat[s:s + 32_000, None, 0].copy(), flat[s:s + 32_000, None, 1].copy(),
                      cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)
            for s in range(0, len(flat), 32_000)]
    out = np.concatenate(rows) if rows else np.empty((0, 3), np.float32)
    return out.reshape(*shape, 3)


def _zncc_cost(ref: np.ndarray, other: np.ndarray) -> np.ndarray:
    """``1 - ZNCC`` over the last two axes (patch pixels, channels); ``ref`` (n, P, 3), ``other`` (..., n, P, 3)."""
    a = ref - ref.mean(axis=(-2, -1), keepdims=True)
    b = other - other.mean(axis=(-2, -1), keepdims=True)
    num = (a * b).sum(axis=(-2, -1))
    den = np.sqrt((a * a).sum(axis=(-2, -1)) * (b * b).sum(axis=(-2, -1)))
    with np.errstate(invalid="ignore", divide="ignore"):
        return 1.0 - np.where(den > 1e-12, num / den, 0.0)


def sweep_depths(cameras: Sequence[Camera], images: Sequence[np.ndarray], index: int, uv: np.ndarray,
                 near: float, far: float, config: SweepConfig = SweepConfig()) -> np.ndarray:
    """z-depths (n,) of pixels ``uv`` (n, 2) of view ``index``, measured by a plane sweep; NaN where not measured.

    Parameters
    ----------
    cameras, images : sequences of Camera and float32 (H, W, 3) images in [0, 1]
        The posed views (the same order in both).
    index : int
        The view the pixels belong to.
    uv : ndarray, shape (n, 2)
        Continuous pixel positions of that view (Nimbus convention: pixel ``u`` spans ``[u, u + 1)``).
    near, far : float
        The depth range swept (``0 < near < far``).
    config : SweepConfig
    """
    if not (0 < near < far and np.isfinite(far)):
        raise NimbusError(f"sweep depth range must satisfy 0 < near < far < inf, got near={near}, far={far}")
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    depth = np.full(len(uv), np.nan)
    others = neighbour_views(cameras, index, config.neighbours, config.max_axis_angle)
    if len(uv) == 0 or len(others) < 2:
        return depth
    ref_cam, ref_img = cameras[index], images[index]
    r = config.patch
    oy, ox = np.mgrid[-r:r + 1, -r:r + 1]
    offsets = np.stack([ox.ravel(), oy.ravel()], 1).astype(np.float64)  # (P, 2)
    patch_uv = uv[:, None, :] + offsets[None]  # (n, P, 2)
    ref_patch = _sample(ref_img, patch_uv)  # (n, P, 3)
    textured = ref_patch.reshape(len(uv), -1).std(axis=1) >= config.min_std
    if not textured.any():
        return depth
    idx = np.flatnonzero(textured)
    patch_uv, ref_patch = patch_uv[idx], ref_patch[idx]
    rays = np.stack([(patch_uv[..., 0] - ref_cam.cx) / ref_cam.fx, (patch_uv[..., 1] - ref_cam.cy) / ref_cam.fy,
                     np.ones(patch_uv.shape[:2])], -1)  # (n, P, 3), z = 1
    inv = np.linspace(1.0 / near, 1.0 / far, config.steps)
    costs = np.full((len(others), config.steps, len(idx)), np.nan)
    for k, j in enumerate(others):
        cam, img = cameras[j], images[j]
        # A point at depth z on pixel ray r: x_w = R^T (z r - t); in camera j: R_j x_w + t_j = z A r + b.
        A = cam.R @ ref_cam.R.T
        b = cam.t - A @ ref_cam.t
        Ar = (rays @ A.T).astype(np.float32)  # (n, P, 3)
        p = Ar[None] / inv.astype(np.float32)[:, None, None, None] + b.astype(np.float32)  # (steps, n, P, 3)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = cam.fx * p[..., 0] / z + cam.cx
            v = cam.fy * p[..., 1] / z + cam.cy
        inside = ((z > 1e-9) & (u >= 0.5) & (u <= cam.width - 0.5) & (v >= 0.5)
                  & (v <= cam.height - 0.5)).all(axis=-1)  # (steps, n)
        s_idx, n_idx = np.nonzero(inside)
        if len(s_idx):
            colours = _sample(img, np.stack([u[s_idx, n_idx], v[s_idx, n_idx]], -1))  # (m, P, 3)
            costs[k, s_idx, n_idx] = _zncc_cost(ref_patch[n_idx], colours)
    valid = np.isfinite(costs)
    enough = valid.sum(axis=0) >= 2  # (steps, n)
    keep = max(2, (len(others) + 1) // 2)
    ordered = np.sort(np.where(valid, costs, np.inf), axis=0)[:keep]  # the better half per depth
    finite = np.isfinite(ordered)
    agg = np.where(enough, np.where(finite, ordered, 0.0).sum(axis=0) / np.maximum(finite.sum(axis=0), 1), np.nan)
    measurable = np.isfinite(agg).any(axis=0)
    if not measurable.any():
        return depth
    filled = np.where(np.isfinite(agg), agg, np.inf)
    best = filled.argmin(axis=0)
    cols = np.arange(len(idx))
    best_cost = filled[best, cols]
    steps = np.arange(config.steps)[:, None]
    away = np.abs(steps - best[None]) > config.exclusion
    rival = np.where(away, filled, np.inf).min(axis=0)
    ok = measurable & (best_cost <= config.max_cost) & (rival >= best_cost + config.margin)
    # Sub-step refinement: a parabola through the best cost and its two neighbours, in inverse depth.
    lo, hi = np.maximum(best - 1, 0), np.minimum(best + 1, config.steps - 1)
    c0, c1, c2 = filled[lo, cols], best_cost, filled[hi, cols]
    interior = (best > 0) & (best < config.steps - 1) & np.isfinite(c0) & np.isfinite(c2)
    with np.errstate(invalid="ignore", divide="ignore"):
        curve = c0 - 2 * c1 + c2
        shift = np.where(interior & (curve > 1e-12), 0.5 * (c0 - c2) / curve, 0.0)
    shift = np.clip(shift, -0.5, 0.5)
    step = inv[1] - inv[0]
    w = inv[best] + shift * step
    depth[idx[ok]] = 1.0 / w[ok]
    return depth


__all__ = ["SweepConfig", "neighbour_views", "sweep_depths"]
