"""Multi-view consistency of per-view depth maps: does view i's depth agree with its neighbour's?

Haze is a function of depth, so two views that disagree about a surface's depth
give it two different hazes.  :func:`depth_consistency` measures this per view:

1. **Neighbour.**  Each view is paired with the nearest other view: the smallest
   distance between camera centres, ties broken by the smallest angle between
   the optical axes (:func:`nearest_views`).
2. **Reprojection.**  Every pixel centre of view i is lifted to 3D with its
   depth ``z_i`` and projected into the neighbour j, giving a pixel position and
   the depth ``z'`` that point has in j.  A pixel with infinite depth (sky) is
   a direction: it projects with ``z' = inf``.
3. **Comparison** with j's depth at the 2 x 2 pixels whose centres surround the
   reprojected position (the point lies between them, so any of them may hold
   its surface), with the relative tolerance ``tol`` (5 %):

   - *outside*: the point falls outside j's image or behind j: not counted;
   - *sky in both*: ``z'`` and j's depth at the nearest pixel are infinite: not counted;
   - *agree*: one of the 2 x 2 depths ``d`` has ``|d - z'| <= tol * z'``;
   - *occluded*: j's depth at the nearest pixel is nearer than ``z' * (1 - tol)``:
     another surface hides the point from j, which therefore says nothing about
     it; not counted.  (This is what any visibility test can do from two depth
     maps alone; it excuses a view i whose depth is too *far*.  The check runs in
     both directions whenever the two views are each other's nearest, as on an
     orbit or a grid, so such an error is caught from the other side.)
   - *disagree*: everything else (j sees farther, or sky, where i puts a surface).

The view's figure is ``agree / (agree + disagree)``; the scene's is the mean
over views that had any pixel counted.  Exact depth scores ~1 (pixels at depth
edges are the exception); depth densified view by view from sparse points scores
lower wherever its guesses between the points differ between views.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Callable, Sequence

import numpy as np

from nimbus.data.camera import Camera
from nimbus.errors import NimbusError

#: Relative depth difference still counted as agreement.
CONSISTENCY_TOLERANCE = 0.05


@dataclass(frozen=True)
class PairConsistency:
    """Counts of one view's pixels reprojected into its neighbour (module docstring).

    Attributes
    ----------
    view, neighbour : str
    agree, disagree, occluded, outside, sky : int
        Pixels in each class.
    fraction : float or None
        ``agree / (agree + disagree)``; None when no pixel was counted.
    """

    view: str
    neighbour: str
    agree: int
    disagree: int
    occluded: int
    outside: int
    sky: int
    fraction: float | None

    def to_dict(self) -> dict:
        return asdict(self)


def nearest_views(cameras: Sequence[Camera]) -> np.ndarray:
    """Index of each camera's nearest other camera (centre distance, then optical-axis angle); (N,) int64."""
    n = len(cameras)
    if n < 2:
        raise NimbusError(f"depth consistency needs at least 2 views, got {n}")
    centres = np.stack([c.center for c in cameras])
    axes = np.stack([c.R[2] for c in cameras])
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    cos = np.clip(axes @ axes.T, -1, 1)
    out = np.empty(n, np.int64)
    for i in range(n):
        others = np.array([j for j in range(n) if j != i])
        # Distances equal to ~1e-9 of the rig size count as ties (co-located cameras).
        d = np.round(dist[i, others] / max(float(dist.max()), 1e-12), 9)
        out[i] = others[np.lexsort((-cos[i, others], d))[0]]
    return out


def pair_consistency(cam_i: Camera, depth_i: np.ndarray, cam_j: Camera, depth_j: np.ndarray,
                     tol: float = CONSISTENCY_TOLERANCE, names: tuple[str, str] = ("i", "j")) -> PairConsistency:
    """Reproject view i's depth into view j and classify every pixel (module docstring)."""
    zi = np.asarray(depth_i, np.float64)
    zj = np.asarray(depth_j, np.float64)
    if zi.shape != (cam_i.height, cam_i.width) or zj.shape != (cam_j.height, cam_j.width):
        raise NimbusError(f"depth maps {zi.shape} and {zj.shape} do not match their cameras")
    rays = cam_i.pixel_rays(np.float64).reshape(-1, 3)
    z = zi.ravel()
    finite = np.isfinite(z) & (z > 0)
    # World points (finite depth) or world directions (sky), then into j's camera frame.
    Rij = cam_j.R @ cam_i.R.T
    dirs = rays @ Rij.T  # rotation part
    pts = np.where(finite[:, None], z[:, None] * dirs + (cam_j.t - Rij @ cam_i.t), dirs)
    zp = pts[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cam_j.fx * pts[:, 0] / zp + cam_j.cx
        v = cam_j.fy * pts[:, 1] / zp + cam_j.cy
    W, H = cam_j.width, cam_j.height
    inside = (zp > 1e-12) & np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    inside &= (z > 0) | ~np.isfinite(z)  # a zero or NaN depth is no surface and no direction
    zprime = np.where(finite, zp, np.inf)
    ui, vi = u[inside], v[inside]
    target = zprime[inside]
    near = zj[vi.astype(np.int64), ui.astype(np.int64)]
    # The 2 x 2 pixels whose centres surround (u, v), clamped at the border.
    u0 = np.clip(np.floor(ui - 0.5).astype(np.int64), 0, W - 1)
    v0 = np.clip(np.floor(vi - 0.5).astype(np.int64), 0, H - 1)
    u1, v1 = np.minimum(u0 + 1, W - 1), np.minimum(v0 + 1, H - 1)
    agree = np.zeros(len(target), bool)
    with np.errstate(invalid="ignore"):
        for uu, vv in ((u0, v0), (u1, v0), (u0, v1), (u1, v1)):
            d = zj[vv, uu]
            agree |= np.isfinite(target) & (np.abs(d - target) <= tol * target)
    sky = ~np.isfinite(target) & ~np.isfinite(near)
    occluded = ~agree & ~sky & (near < target * (1 - tol))
    disagree = ~agree & ~sky & ~occluded
    a, dis = int(agree.sum()), int(disagree.sum())
    return PairConsistency(names[0], names[1], a, dis, int(occluded.sum()), int((~inside).sum()), int(sky.sum()),
                           a / (a + dis) if a + dis else None)


def depth_consistency(cameras: Sequence[Camera], depth_of: Callable[[int], np.ndarray],
                      names: Sequence[str] | None = None, tol: float = CONSISTENCY_TOLERANCE) -> dict:
    """Per-view and mean depth consistency of a scene (module docstring).

    Parameters
    ----------
    cameras : sequence of Camera
    depth_of : callable
        ``depth_of(i)`` -> view i's z-depth (H, W), ``inf`` = no surface; called
        twice per view (as the view and as a neighbour), so it may load lazily.
    names : sequence of str, optional
    tol : float
        Relative tolerance (default 5 %).

    Returns
    -------
    dict
        ``mean`` (float or None), ``tolerance``, ``views`` (list of
        :meth:`PairConsistency.to_dict`).
    """
    names = list(names) if names is not None else [str(i) for i in range(len(cameras))]
    pairs = nearest_views(cameras)
    views = [pair_consistency(cameras[i], depth_of(i), cameras[j], depth_of(j), tol, (names[i], names[j]))
             for i, j in enumerate(pairs)]
    fracs = [p.fraction for p in views if p.fraction is not None]
    return {"mean": float(np.mean(fracs)) if fracs else None, "tolerance": tol,
            "views": [p.to_dict() for p in views]}


def scene_depth_consistency(scene, depth_of_view: Callable, tol: float = CONSISTENCY_TOLERANCE) -> dict | None:
    """The manifest's figure for a scene: ``mean``, ``tolerance`` and each view's fraction and neighbour.

    ``depth_of_view(view)`` gives a :class:`nimbus.data.View`'s depth (the
    synthesizer's, sky at ``inf``).  None for a scene of one view (no neighbour).
    Fractions are rounded to 1e-4: the figure is a summary, not a fingerprint.
    """
    views = scene.views
    if len(views) < 2:
        return None
    full = depth_consistency([v.camera for v in views], lambda i: depth_of_view(views[i]), [v.name for v in views],
                             tol)
    return {"mean": None if full["mean"] is None else round(full["mean"], 4), "tolerance": tol,
            "views": {p["view"]: {"neighbour": p["neighbour"],
                                  "fraction": None if p["fraction"] is None else round(p["fraction"], 4)}
                      for p in full["views"]}}
