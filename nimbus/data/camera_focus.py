"""Where posed cameras look, and random starting points placed there for a scene without sparse points.

3DGS starts from sparse points.  A capture that has poses but none (a transforms.json export, a
COLMAP model with an empty ``points3D``) first gets triangulated points
(:mod:`nimbus.data.triangulate`); where that finds too few, the Gaussians start from random points,
and this module decides where, from the cameras alone:

* **focus** (inward captures: an orbit, a turntable, an arc around an object).  The point nearest,
  in the least-squares sense, to every optical axis (the line through camera centre ``c_i`` along
  unit viewing direction ``d_i``) solves the 3 x 3 system

      sum_i (I - d_i d_i^T) p = sum_i (I - d_i d_i^T) c_i.

  Points are drawn uniformly in a ball about ``p`` of radius
  :attr:`RandomInitConfig.focus_radius_factor` times the median camera distance to ``p``.
* **forward** (forward-facing captures, LLFF-style grids, and anything whose axes do not meet in
  front of the cameras).  The axes are nearly parallel, so the system above is ill-conditioned and
  its solution meaningless; instead each point is drawn in the view frustum of a random camera, at
  a random pixel, with inverse depth uniform between ``1/far`` and ``1/near`` (as NeRF samples
  forward-facing scenes): ``near`` is the depth at which the cameras' views start to overlap
  (camera spread / tan(half field of view), times :attr:`RandomInitConfig.forward_near_factor`) and
  ``far`` is :attr:`RandomInitConfig.forward_depth_ratio` times ``near``.

Which one applies (:func:`plan_random_points`): the smallest eigenvalue of the system matrix over
the number of cameras is ``min_e mean_i sin^2(angle(d_i, e))``, so its square root is the RMS sine of
the axes' angle about their best common direction; the focus is used when that angle
(:attr:`CameraFocus.axis_spread_deg`) is at least :attr:`RandomInitConfig.min_axis_spread_deg` and
the focus lies in front of at least :attr:`RandomInitConfig.min_front_fraction` of the cameras.
A full orbit has a spread of 45 degrees or more (built-in garden 47, tabletop 50); the built-in
street grid (cameras 2 m apart, all looking at a point 40 m ahead) 1.2 degrees.

The previous rule (a cube about the mean camera centre) put an inward capture's points among the
cameras instead of on the subject they surround.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from nimbus.data.camera import Camera
from nimbus.errors import NimbusError


@dataclass(frozen=True)
class RandomInitConfig:
    """Where random starting points go (see the module docstring).

    Attributes
    ----------
    focus_radius_factor : float
        Radius of the ball of points about the focus, in units of the median camera distance to it
        (default 0.5: an orbit at distance D fills a ball of radius D/2, which holds the subject and
        keeps points off the cameras; 3DGS's Blender cube, half-width 1.3 for cameras at distance 4,
        is about 0.33 of it).
    min_axis_spread_deg : float
        Smallest RMS angle, in degrees, of the optical axes about their best common direction for
        the focus to be used (default 5: a 20-degree arc around an object has about 5.8).
    min_front_fraction : float
        Smallest fraction of the cameras the focus must lie in front of (default 0.75); axes that
        meet behind the cameras (an outward-facing ring) are treated as forward-facing.
    forward_near_factor : float
        ``near`` of forward-facing sampling in units of spread / tan(half field of view), where the
        spread is the largest distance of a camera centre from their mean (default 1.0).
    forward_depth_ratio : float
        ``far / near`` of forward-facing sampling (default 100: the built-in street, whose content
        lies at 1.9 to 157 m, gets near 2.5 m and far 250 m).
    """

    focus_radius_factor: float = 0.5
    min_axis_spread_deg: float = 5.0
    min_front_fraction: float = 0.75
    forward_near_factor: float = 1.0
    forward_depth_ratio: float = 100.0

    def __post_init__(self) -> None:
        if not self.focus_radius_factor > 0 or not self.forward_near_factor > 0:
            raise NimbusError("focus_radius_factor and forward_near_factor must be positive")
        if not 0 <= self.min_axis_spread_deg <= 90:
            raise NimbusError(f"min_axis_spread_deg must be in [0, 90], got {self.min_axis_spread_deg}")
        if not 0 <= self.min_front_fraction <= 1:
            raise NimbusError(f"min_front_fraction must be in [0, 1], got {self.min_front_fraction}")
        if not self.forward_depth_ratio > 1:
            raise NimbusError(f"forward_depth_ratio must be > 1, got {self.forward_depth_ratio}")


@dataclass(frozen=True)
class CameraFocus:
    """The least-squares meeting point of the optical axes and how well it is determined.

    Attributes
    ----------
    point : ndarray, shape (3,), or None
        The focus; None when the axes are parallel (singular system).
    axis_spread_deg : float
        RMS angle of the axes about their best common direction, degrees (0 for parallel axes).
    front_fraction : float
        Fraction of the cameras the focus lies in front of (0 when ``point`` is None).
    median_distance : float
        Median distance of the camera centres from the focus (inf when ``point`` is None).
    """

    point: np.ndarray | None
    axis_spread_deg: float
    front_fraction: float
    median_distance: float


def optical_axes(cameras: Sequence[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (N, 3) and unit viewing directions (N, 3) (each camera's +z axis in the world)."""
    if not cameras:
        raise ValueError("no cameras")
    centers = np.stack([c.center for c in cameras]).astype(np.float64)
    directions = np.stack([np.asarray(c.R, np.float64)[2] for c in cameras])  # R^T @ (0, 0, 1)
    return centers, directions / np.linalg.norm(directions, axis=1, keepdims=True)


def camera_focus(centers: np.ndarray, directions: np.ndarray) -> CameraFocus:
    """The point nearest to every line ``centers[i] + s * directions[i]`` (least squares), with diagnostics.

    Parameters
    ----------
    centers : ndarray, shape (N, 3)
        Camera centres.
    directions : ndarray, shape (N, 3)
        Viewing directions (normalised here).

    Returns
    -------
    CameraFocus
        Solves ``sum_i (I - d_i d_i^T) p = sum_i (I - d_i d_i^T) c_i``.
    """
    c = np.asarray(centers, np.float64).reshape(-1, 3)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    if len(c) != len(d) or not len(c):
        raise ValueError(f"need as many directions as centres (and at least one), got {len(c)} and {len(d)}")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # (N, 3, 3): projection off each axis
    a = proj.sum(0)
    b = np.einsum("nij,nj->i", proj, c)
    lam = float(np.linalg.eigvalsh(a)[0]) / len(c)
    spread = math.degrees(math.asin(math.sqrt(min(max(lam, 0.0), 1.0))))
    if lam <= 1e-12:
        return CameraFocus(None, spread, 0.0, math.inf)
    p = np.linalg.solve(a, b)
    along = np.einsum("ni,ni->n", p[None] - c, d)
    return CameraFocus(p, spread, float(np.mean(along > 0)), float(np.median(np.linalg.norm(p[None] - c, axis=1))))


@dataclass(frozen=True)
class RandomInitPlan:
    """Where :func:`sample_random_points` draws (see the module docstring).

    Attributes
    ----------
    kind : str
        ``"focus"`` (a ball about the cameras' focus) or ``"forward"`` (the view frusta between
        ``near`` and ``far``).
    focus : CameraFocus
        The focus diagnostics (also for ``"forward"``: why the focus was not used).
    radius : float or None
        Ball radius (``"focus"``).
    near, far : float or None
        Depth range (``"forward"``), z-depth in world units.
    reason : str
        Why the focus was not used (``"forward"``).
    """

    kind: str
    focus: CameraFocus
    radius: float | None = None
    near: float | None = None
    far: float | None = None
    reason: str = ""

    def to_dict(self) -> dict:
        """JSON-ready, for run records."""
        f = self.focus
        out = {"kind": self.kind, "axis_spread_deg": round(f.axis_spread_deg, 3),
               "front_fraction": round(f.front_fraction, 3)}
        if self.kind == "focus":
            out.update(center=[round(float(x), 6) for x in f.point], radius=round(float(self.radius), 6))
        else:
            out.update(near=round(float(self.near), 6), far=round(float(self.far), 6), reason=self.reason)
        return out

    def describe(self) -> str:
        """One phrase: where the points go and why."""
        f = self.focus
        if self.kind == "focus":
            centre = ", ".join(f"{x:.3g}" for x in f.point)
            return (f"a ball of radius {self.radius:.3g} about the cameras' focus ({centre}) (axes spread "
                    f"{f.axis_spread_deg:.1f} deg)")
        return f"the cameras' view frusta at depths {self.near:.3g} to {self.far:.3g} ({self.reason})"


def plan_random_points(cameras: Sequence[Camera], config: RandomInitConfig = RandomInitConfig()) -> RandomInitPlan:
    """Decide where random starting points go for ``cameras`` (see the module docstring)."""
    centers, directions = optical_axes(cameras)
    focus = camera_focus(centers, directions)
    if (focus.point is not None and focus.axis_spread_deg >= config.min_axis_spread_deg
            and focus.front_fraction >= config.min_front_fraction):
        return RandomInitPlan("focus", focus, radius=config.focus_radius_factor * focus.median_distance)
    spread = float(np.max(np.linalg.norm(centers - centers.mean(0), axis=1)))
    if spread < 1e-8:  # one camera position: no length scale at all; 1 is the scene extent's own fallback
        spread = 1.0
    half_fov = float(np.median([min(math.atan(0.5 * c.width / c.fx), math.atan(0.5 * c.height / c.fy))
                                for c in cameras]))
    near = config.forward_near_factor * spread / math.tan(half_fov)
    if focus.point is None or focus.axis_spread_deg < config.min_axis_spread_deg:
        reason = (f"forward-facing: the optical axes are nearly parallel, spread {focus.axis_spread_deg:.2g} deg "
                  f"< {config.min_axis_spread_deg:g}")
    else:
        reason = (f"the optical axes meet in front of only {focus.front_fraction:.0%} of the cameras "
                  f"(< {config.min_front_fraction:.0%})")
    return RandomInitPlan("forward", focus, near=near, far=config.forward_depth_ratio * near, reason=reason)


def sample_random_points(plan: RandomInitPlan, cameras: Sequence[Camera], n: int,
                         seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random points where ``plan`` says, and random colours.

    Returns
    -------
    points : ndarray, shape (n, 3), float64
    colors : ndarray, shape (n, 3), float32 in [0, 1]
    """
    rng = np.random.default_rng([seed, 36])
    if plan.kind == "focus":
        v = rng.normal(size=(n, 3))
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        r = plan.radius * rng.random(n) ** (1.0 / 3.0)  # uniform in the ball's volume
        points = plan.focus.point[None] + v * r[:, None]
    elif plan.kind == "forward":
        which = rng.integers(0, len(cameras), n)
        u, v, s = rng.random(n), rng.random(n), rng.random(n)
        z = 1.0 / (1.0 / plan.far + s * (1.0 / plan.near - 1.0 / plan.far))
        points = np.empty((n, 3))
        for i, cam in enumerate(cameras):
            k = which == i
            x = (u[k] * cam.width - cam.cx) / cam.fx * z[k]
            y = (v[k] * cam.height - cam.cy) / cam.fy * z[k]
            local = np.stack([x, y, z[k]], axis=1)
            points[k] = (local - np.asarray(cam.t)[None]) @ np.asarray(cam.R)  # R^T (x - t)
    else:
        raise ValueError(f"unknown plan kind {plan.kind!r}")
    colors = rng.random((n, 3)).astype(np.float32)
    return points, colors


__all__ = ["CameraFocus", "RandomInitConfig", "RandomInitPlan", "camera_focus", "optical_axes",
           "plan_random_points", "sample_random_points"]
