"""A sparse point cloud "like SfM points", taken from rendered depth maps.

3DGS starts from SfM points; a built-in scene has exact geometry, so it gets
its points by unprojecting pixels of some training views with their rendered
z-depths (skipping the backdrop, like SfM skips the sky), merging points that
fall in the same voxel, and keeping at most a fixed number.  Deterministic
for a given seed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from nimbus.data.camera import Camera


@dataclass(frozen=True)
class PointCloudConfig:
    """How the sparse points are sampled.

    Attributes
    ----------
    view_stride : int
        Use every ``view_stride``-th training view (default 2).
    pixel_stride : int
        Unproject every ``pixel_stride``-th pixel in both directions (default 3), starting
        at a seed-dependent phase.
    voxel_fraction : float
        Voxel edge for merging, as a fraction of the median sampled depth (default 0.01).
    max_points : int
        Keep at most this many points, chosen at random with the seed (default 4000).
    include_backdrop : bool
        Also unproject backdrop pixels (default False: skipped, as SfM skips a featureless
        sky).  The built-in backdrop is a textured surface at a finite distance (hills,
        clouds) that SfM would triangulate.  Its points are merged in voxels that grow
        with distance (octaves of the median distance of the non-backdrop points), so far
        content keeps about the density per pixel that near surfaces have instead of one
        point per pixel per view.
    """

    view_stride: int = 2
    pixel_stride: int = 3
    voxel_fraction: float = 0.01
    max_points: int = 4000
    include_backdrop: bool = False


def sample_points(cameras: Sequence[Camera], images: Sequence[np.ndarray], depths: Sequence[np.ndarray],
                  masks: Sequence[np.ndarray], config: PointCloudConfig, seed: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Unproject strided non-backdrop pixels of the given views and deduplicate them.

    Parameters
    ----------
    cameras : sequence of Camera
    images : sequence of ndarray, each (H, W, 3) float32 in [0, 1]
    depths : sequence of ndarray, each (H, W) float32 z-depth
    masks : sequence of ndarray, each (H, W) bool, True on the backdrop (skipped)
    config : PointCloudConfig
    seed : int

    Returns
    -------
    points : ndarray, shape (N, 3), float64
    colors : ndarray, shape (N, 3), uint8
    """
    rng = np.random.default_rng([seed, 5])
    pts, cols, backdrop = [], [], []
    chosen = range(0, len(cameras), max(config.view_stride, 1))
    for i in chosen:
        cam, img, dep, msk = cameras[i], images[i], depths[i], masks[i]
        ps = max(config.pixel_stride, 1)
        ov, ou = rng.integers(0, ps, 2)
        rays = cam.pixel_rays(np.float64)[ov::ps, ou::ps]
        z = dep[ov::ps, ou::ps].astype(np.float64)
        keep = np.isfinite(z) & (z > 0)
        if not config.include_backdrop:
            keep &= ~msk[ov::ps, ou::ps]
        p_cam = rays[keep] * z[keep][:, None]
        pts.append((p_cam - cam.t) @ cam.R)  # camera -> world: R^T (p - t)
        cols.append(img[ov::ps, ou::ps][keep])
        backdrop.append(msk[ov::ps, ou::ps][keep])
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    points = np.concatenate(pts)
    colors = np.concatenate(cols)
    if len(points) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    dist = np.linalg.norm(points - np.mean([c.center for c in cameras], axis=0), axis=1)
    surface = ~np.concatenate(backdrop)
    median = max(float(np.median(dist[surface] if surface.any() else dist)), 1e-6)
    voxel = max(config.voxel_fraction * median, 1e-6)
    if config.include_backdrop:
        # Octave of the distance beyond the median: voxels double with each doubling of distance.
        octave = np.ceil(np.log2(np.maximum(dist / median, 1.0))).astype(np.int64)
        cells = np.floor(points / (voxel * 2.0 ** octave)[:, None]).astype(np.int64)
        keys = np.concatenate([octave[:, None], cells], axis=1)
    else:
        keys = np.floor(points / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    first.sort()  # keep the first sample of each voxel, in sampling order
    if len(first) > config.max_points:
        first = np.sort(rng.choice(first, config.max_points, replace=False))
    colors8 = (np.clip(colors[first], 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return points[first], colors8
