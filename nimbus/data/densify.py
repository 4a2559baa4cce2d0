"""A dense starting cloud from sparse triangulated points: every training view's pixels, the backdrop included.

SIFT on small photos triangulates a few thousand points on the most textured surfaces and none on the
backdrop (far hills, clouds, the end of a street), and 3DGS only grows Gaussians where there are some,
so a run from those points alone leaves the backdrop empty.  :func:`densify_points` adds, per
training view, pixels sampled on a jittered grid, each unprojected with the view's camera at

* the depth a plane sweep measures for it in the view's posed neighbours (:mod:`nimbus.data.sweep`),
  where it measures one (a textured patch whose colours match in one depth only);
* otherwise the depth of the triangulated points projected near it (within ``radius`` of the image diagonal),
  when those agree (their depths within a factor ``1 + depth_tolerance``): a textureless patch
  next to measured ones;
* otherwise, when no triangulated point projects near it, a far depth: ``far_factor`` times the
  ``far_percentile`` of the depths of the points the view sees (of all views' when it sees none):
  the backdrop, where SIFT found nothing;
* and not at all when nearby points disagree (a depth edge, where neither depth is a safe guess),

coloured by the pixel.  The far depth is a guess, not a measurement: 3DGS moves and reshapes those
Gaussians; what matters is that the backdrop has some to grow from.  Everything is seeded, so the
same views, points and seed give the same cloud.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from nimbus.data.scene import View
from nimbus.data.sweep import SweepConfig, sweep_depths
from nimbus.errors import NimbusError


@dataclass(frozen=True)
class DensifyConfig:
    """Settings of :func:`densify_points`.

    Attributes
    ----------
    samples : int
        Pixels sampled over all views (split evenly between them; those at a depth edge are
        dropped).  Default 30,000: about the thousand points per view SfM gives on full-size photos
        (and the built-in scenes have); on the built-in garden 30,000 trained 0.8 dB better than 10,000.
    radius : float
        A triangulated point gives its depth to pixels within this fraction of the image diagonal
        (default 0.03: 9 px at 240 x 180).
    neighbours : int
        Projected points within ``radius`` whose depths are compared (the nearest ones, default 4).
    depth_tolerance : float
        They agree when the largest depth is at most ``1 + depth_tolerance`` times the smallest
        (default 0.25); the sample then takes their median depth.
    far_percentile : float
        Percentile of a view's point depths the far depth is measured from (default 99: the
        farthest points SIFT found, not the subject most of them are on).
    far_factor : float
        The far depth is this many times that percentile (default 3).  On the built-in garden
        (docs/data.md, 10,000 pixels) 99 and 3 trained 0.46 dB better than 95 and 2, which put the backdrop at
        a seventh of the hills' depth.
    sweep : bool
        Measure each sample's depth by a plane sweep first (default True); the rules below it
        apply where the sweep measures nothing.  On the validation garden and street (scene seed 1,
        small), the swept depths of the samples were within 10 % of the true depth for 92 % and 84 %
        of those near triangulated points (66 % and 79 % with their median), and recovered half of
        those at depth edges.
    sweep_config : SweepConfig
    seed : int
        Seed of the grid jitter.
    """

    samples: int = 30_000
    radius: float = 0.03
    neighbours: int = 4
    depth_tolerance: float = 0.25
    far_percentile: float = 99.0
    far_factor: float = 3.0
    sweep: bool = True
    sweep_config: SweepConfig = SweepConfig()
    seed: int = 0

    def __post_init__(self) -> None:
        if self.samples < 1 or self.neighbours < 1:
            raise NimbusError("densify samples and neighbours must be >= 1")
        if not (self.radius > 0 and self.depth_tolerance >= 0 and 0 < self.far_percentile <= 100
                and self.far_factor >= 1):
            raise NimbusError("densify radius must be > 0, depth_tolerance >= 0, far_percentile in (0, 100] and "
                              "far_factor >= 1")


def _grid(width: int, height: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` continuous pixel positions (count, 2): one in each of ``count`` cells of a grid of the image's
    aspect (all but the few that make the grid whole), jittered within it."""
    nx = max(1, round(math.sqrt(count * width / height)))
    ny = max(1, math.ceil(count / nx))
    cx, cy = np.meshgrid(np.arange(nx), np.arange(ny))
    cells = np.stack([cx.ravel(), cy.ravel()], 1).astype(np.float64)
    cells = cells[np.sort(rng.choice(len(cells), count, replace=False))]
    jitter = rng.random(cells.shape)
    return (cells + jitter) * np.array([width / nx, height / ny])


def densify_points(views: Sequence[View], points: np.ndarray, colors: np.ndarray,
                   config: DensifyConfig = DensifyConfig()) -> tuple[np.ndarray, np.ndarray, dict]:
    """The triangulated ``points`` with pixels of ``views`` added (module docstring).

    Parameters
    ----------
    views : sequence of View
        The posed training views (images in memory or on disk).
    points : ndarray, shape (N, 3)
        Triangulated points, world coordinates (N >= 1).
    colors : ndarray, shape (N, 3), uint8
    config : DensifyConfig

    Returns
    -------
    points : ndarray, shape (N + M, 3), float64
        ``points`` first, then the M added samples.
    colors : ndarray, shape (N + M, 3), uint8
    info : dict
        ``samples`` (M), ``swept`` (at a depth the plane sweep measured), ``near`` (taking nearby
        points' depth), ``far`` (at the far depth),
        ``dropped`` (at a depth edge), and the settings.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    cols = np.asarray(colors, np.uint8).reshape(-1, 3)
    views = sorted(views, key=lambda v: v.name)
    if not len(pts) or not views:
        raise NimbusError("densifying needs triangulated points and at least one posed view")
    from scipy.spatial import cKDTree

    pixels = sum(v.camera.width * v.camera.height for v in views)
    if config.samples > pixels:
        raise NimbusError(f"cannot densify with {config.samples} pixels: the {len(views)} training views have "
                          f"{pixels}; set init_densify to at most that (0 turns it off)")
    rng = np.random.default_rng(config.seed)
    per_view = [config.samples // len(views) + (i < config.samples % len(views)) for i in range(len(views))]
    seen_depths = []
    for v in views:
        _, z, seen = v.camera.project_seen(pts)
        seen_depths.append(z[seen])
    all_depths = np.concatenate(seen_depths)
    if not len(all_depths):
        raise NimbusError("no training view sees a triangulated point in front of it; nothing to densify from")
    far_all = config.far_factor * float(np.percentile(all_depths, config.far_percentile))
    # The swept range: half the nearest triangulated depth to ten times the far depth.
    sweep_range = (0.5 * float(np.percentile(all_depths, 1)), 10.0 * far_all)
    cameras = [v.camera for v in views]
    images = [v.load_image() for v in views] if config.sweep else []
    out_pts, out_cols = [pts], [cols]
    swept_n = near_n = far_n = dropped = 0
    for i, (v, depths, count) in enumerate(zip(views, seen_depths, per_view)):
        if count == 0:
            continue
        cam = v.camera
        uv_s = _grid(cam.width, cam.height, count, rng)
        z = np.full(len(uv_s), np.nan)
        far = config.far_factor * float(np.percentile(depths, config.far_percentile)) if len(depths) else far_all
        has_near = np.zeros(len(uv_s), bool)
        if len(depths):
            uv_p, z_p, seen = cam.project_seen(pts)
            tree = cKDTree(uv_p[seen])
            k = min(config.neighbours, int(seen.sum()))
            dist, idx = tree.query(uv_s, k=k, distance_upper_bound=config.radius * math.hypot(cam.width, cam.height))
            dist, idx = dist.reshape(len(uv_s), k), idx.reshape(len(uv_s), k)
            found = np.isfinite(dist)
            has_near = found[:, 0]
            zn = np.where(found, z_p[seen][np.minimum(idx, int(seen.sum()) - 1)], np.nan)
            with np.errstate(invalid="ignore", divide="ignore"):
                agree = np.nanmax(zn[has_near], 1) <= (1 + config.depth_tolerance) * np.nanmin(zn[has_near], 1)
            z[np.flatnonzero(has_near)[agree]] = np.nanmedian(zn[has_near], 1)[agree]
        swept = np.zeros(len(uv_s), bool)
        if config.sweep:
            zs = sweep_depths(cameras, images, i, uv_s, *sweep_range, config=config.sweep_config)
            swept = np.isfinite(zs)
            z[swept] = zs[swept]
        far_here = ~has_near & ~swept
        z[far_here] = far
        swept_n += int(swept.sum())
        near_n += int((has_near & ~swept & np.isfinite(z)).sum())
        dropped += int((has_near & ~swept & ~np.isfinite(z)).sum())
        far_n += int(far_here.sum())
        keep = np.isfinite(z)
        uv_s, z = uv_s[keep], z[keep]
        rays = np.stack([(uv_s[:, 0] - cam.cx) / cam.fx, (uv_s[:, 1] - cam.cy) / cam.fy, np.ones(len(uv_s))], 1)
        cam_pts = rays * z[:, None]
        out_pts.append((cam_pts - cam.t) @ cam.R)  # x_c = R x_w + t
        img = images[i] if images else v.load_image()
        px = np.minimum(uv_s.astype(np.int64), [cam.width - 1, cam.height - 1])
        out_cols.append(np.clip(np.rint(img[px[:, 1], px[:, 0]] * 255), 0, 255).astype(np.uint8))
    settings = {k: getattr(config, k) for k in config.__dataclass_fields__ if k != "sweep_config"}
    if config.sweep:
        settings["sweep_config"] = dataclasses.asdict(config.sweep_config)
    info = {"samples": swept_n + near_n + far_n, "swept": swept_n, "near": near_n, "far": far_n, "dropped": dropped,
            "config": settings}
    return np.concatenate(out_pts), np.concatenate(out_cols), info


__all__ = ["DensifyConfig", "densify_points"]
