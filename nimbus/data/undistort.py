"""Distorted cameras become pinhole views on load: OpenCV resampling, cached by content.

Nimbus renders pinhole cameras only.  The readers (:mod:`nimbus.data.colmap`,
:mod:`nimbus.data.transforms`) turn a camera with lens distortion into a :class:`Lens`
and call :func:`undistort_views`, which replaces each such view by a pinhole view whose
image, depth map, validity mask and sky mask are resampled files in a cache folder.
The input scene is never written to.

What is decided here
--------------------
* **Lens models.** A :class:`Lens` is one of OpenCV's two distortion models: the
  perspective (Brown-Conrady / rational) model of ``cv2.projectPoints`` with
  ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``, or the equidistant fisheye model of
  ``cv2.fisheye`` with ``(k1, k2, k3, k4)``.  COLMAP's and nerfstudio's models map onto
  these exactly (the readers hold the tables); the maths is OpenCV's, not ours.
* **The pinhole camera that replaces a distorted one** keeps the rotation, the camera
  centre and the focal lengths ``fx, fy``; its image is the largest axis-aligned rectangle
  of the undistorted image plane in which *every pixel has source data* (the inner
  envelope of the source image's border, undistorted), at most :data:`MAX_SCALE` times the
  source size.  This is ``colmap image_undistorter``'s default (``blank_pixels=0``), so no
  pixel of the result is invalid and nothing downstream needs a mask for it.  Should a
  border pixel still sample outside the source (rounding), it is marked invalid in
  ``View.mask`` (True = the pixel counts), together with the source's own validity mask.
* **Resampling.** Images: bicubic (:data:`IMAGE_INTERPOLATION`), clipped to [0, 1], stored
  as 8-bit PNG.  Validity and sky masks: nearest neighbour.  Depth maps: inverse depth
  bilinearly, except at depth edges, where the nearest pixel's depth is kept (never a blend
  of two surfaces), and the values stay z-depths: undistortion moves pixels but not the
  camera centre or axes, so a surface point's z-depth (its camera-frame z) is the same in
  both images (:meth:`Undistortion.depth`).  Sparse points are 3D and do not change.
* **Pixel centres.** Nimbus puts pixel (u, v)'s centre at (u + 0.5, v + 0.5); OpenCV's maps
  use (u, v).  Every intrinsic matrix handed to OpenCV is shifted by half a pixel
  (:func:`opencv_matrix`), so the maps are exact under Nimbus's convention.
* **Cache.** One folder per resampled file, ``<cache>/<key>/<kind>.<ext>`` with
  ``<cache>`` = ``$NIMBUS_CACHE/undistorted`` (default ``~/.cache/nimbus/undistorted``,
  :func:`nimbus.utils.fs.cache_root`) and ``<key>`` the SHA-256 of the source file's bytes,
  the source camera, the lens, the output camera, :data:`UNDISTORT_VERSION` and the OpenCV
  version.  A changed photo, calibration or algorithm gets a new entry; a second load
  reads the entry.  Files are written atomically, so concurrent loads are safe.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from nimbus.data.camera import Camera
from nimbus.data.images import encode_png
from nimbus.data.scene import View
from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_write_bytes, cache_root

log = logging.getLogger(__name__)

#: Bump when the same input would give different output files (invalidates every cache entry).
UNDISTORT_VERSION = 1
#: Sub-folder of the Nimbus cache folder that holds undistorted files.
CACHE_SUBDIR = "undistorted"
#: Largest output side over the source side (COLMAP's ``max_scale``): a wide fisheye's pinhole
#: image would otherwise grow without bound towards 90 degrees off axis.
MAX_SCALE = 2.0
#: Smallest output side over the source side (COLMAP's ``min_scale``): below it the calibration is
#: almost certainly wrong, and the crop would throw most of the photo away.
MIN_SCALE = 0.2
#: How far (pixels) a point may miss its source position after undistortion and distortion again,
#: and how far outside the source image an output pixel may sample and still count as valid.
ROUND_TRIP_TOLERANCE_PX = 0.01
#: Iterations and tolerance of OpenCV's point undistortion (its default, 5 iterations, misses by
#: several thousandths of a pixel on an ordinary phone lens).
POINT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
#: Image resampling: bicubic keeps more detail than bilinear where the output magnifies the source.
IMAGE_INTERPOLATION = cv2.INTER_CUBIC
#: Relative difference up to which an interpolated depth is trusted over the nearest pixel's
#: (larger differences are depth edges, where a blend would be a surface that is not there).
DEPTH_EDGE_TOLERANCE = 0.05
#: Normalised radius given to a fisheye border point that lies at or beyond 90 degrees off axis
#: (no pinhole image can show it; it then never limits the crop, :data:`MAX_SCALE` does).
_BEYOND_PINHOLE = 1e6

PERSPECTIVE_COEFFS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
FISHEYE_COEFFS = ("k1", "k2", "k3", "k4")


@dataclass(frozen=True)
class Lens:
    """Lens distortion in OpenCV's terms (the pinhole part ``fx, fy, cx, cy`` is the view's camera).

    Attributes
    ----------
    model : str
        The model as the scene file names it (``"OPENCV"``, ``"SIMPLE_RADIAL_FISHEYE"``, ...),
        for messages and the cache key.
    fisheye : bool
        True: OpenCV's equidistant fisheye model (``cv2.fisheye``), ``theta_d = theta (1 + k1 theta^2
        + k2 theta^4 + k3 theta^6 + k4 theta^8)``.  False: the perspective model of ``cv2.projectPoints``.
    coeffs : tuple of float
        OpenCV's distortion vector: ``(k1, k2, k3, k4)`` for a fisheye; ``(k1, k2, p1, p2)``,
        ``(k1, k2, p1, p2, k3)`` or ``(k1, k2, p1, p2, k3, k4, k5, k6)`` (rational model) otherwise.
        Dimensionless (they act on normalised image coordinates), so they hold at any image scale.
    """

    model: str
    fisheye: bool
    coeffs: tuple[float, ...]

    def __post_init__(self) -> None:
        coeffs = tuple(float(c) for c in self.coeffs)
        allowed = (4,) if self.fisheye else (4, 5, 8)
        if len(coeffs) not in allowed:
            raise ValueError(f"{'fisheye' if self.fisheye else 'perspective'} lens takes {allowed} coefficients, "
                             f"got {len(coeffs)}")
        names = FISHEYE_COEFFS if self.fisheye else PERSPECTIVE_COEFFS
        for name, c in zip(names, coeffs):
            if not np.isfinite(c):
                raise NimbusError(f"lens distortion {name} of the {self.model} model must be finite, got {c}")
        # One spelling per lens (trailing zero terms dropped), so equal lenses compare and cache as equal.
        while not self.fisheye and len(coeffs) > 4 and not any(coeffs[4 if len(coeffs) == 5 else 5:]):
            coeffs = coeffs[:4] if len(coeffs) == 5 else coeffs[:5]
        object.__setattr__(self, "coeffs", coeffs)

    @property
    def dist(self) -> np.ndarray:
        """The coefficients as the float64 vector OpenCV takes."""
        return np.array(self.coeffs, dtype=np.float64)

    @property
    def is_identity(self) -> bool:
        """True for a perspective lens without distortion (a fisheye always needs resampling)."""
        return not self.fisheye and not any(self.coeffs)

    def describe(self) -> str:
        """``"OPENCV (k1=-0.2, k2=0.05)"``: the model and its non-zero coefficients."""
        names = FISHEYE_COEFFS if self.fisheye else PERSPECTIVE_COEFFS
        values = ", ".join(f"{n}={c:.4g}" for n, c in zip(names, self.coeffs) if c)
        return f"{self.model} ({values})" if values else self.model


def opencv_matrix(camera: Camera) -> np.ndarray:
    """The 3x3 intrinsic matrix in OpenCV's pixel convention (pixel u's centre at u, not u + 0.5)."""
    K = camera.K
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    return K


def distort_points(xy: np.ndarray, camera: Camera, lens: Lens) -> np.ndarray:
    """Pixel positions (N, 2), Nimbus convention, of normalised undistorted image points ``xy`` (N, 2).

    ``xy = (X / Z, Y / Z)`` of camera-frame points in front of the camera; ``camera`` gives
    the distorted camera's ``fx, fy, cx, cy``.
    """
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    K = opencv_matrix(camera)
    if lens.fisheye:
        px = cv2.fisheye.distortPoints(xy.reshape(-1, 1, 2), K, lens.dist)
    else:
        rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        px, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, lens.dist)
    return px.reshape(-1, 2) + 0.5


def undistort_points(px: np.ndarray, camera: Camera, lens: Lens) -> np.ndarray:
    """Normalised undistorted image points (N, 2) of pixel positions ``px`` (N, 2), Nimbus convention.

    The inverse of :func:`distort_points` (OpenCV's iterative solver, run to
    :data:`POINT_CRITERIA`).  A fisheye point at or beyond 90 degrees off axis has no
    pinhole image: it comes back along its direction at a radius of ``1e6``.  Points that
    do not map back onto themselves within :data:`ROUND_TRIP_TOLERANCE_PX` come back as NaN.
    """
    px = np.asarray(px, np.float64).reshape(-1, 2)
    K = opencv_matrix(camera)
    src = (px - 0.5).reshape(-1, 1, 2)
    if lens.fisheye:
        xy = cv2.fisheye.undistortPoints(src, K, lens.dist, criteria=POINT_CRITERIA).reshape(-1, 2)
    else:
        xy = cv2.undistortPoints(src, K, lens.dist, criteria=POINT_CRITERIA).reshape(-1, 2)
    with np.errstate(invalid="ignore"):
        back = distort_points(np.nan_to_num(xy), camera, lens)
        missed = ~(np.linalg.norm(back - px, axis=1) <= ROUND_TRIP_TOLERANCE_PX)
    if lens.fisheye and missed.any():
        # An equidistant lens images angles up to (and past) 90 degrees; the pinhole cannot.
        d = (px[missed] - [camera.cx, camera.cy]) / [camera.fx, camera.fy]
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        xy[missed] = _BEYOND_PINHOLE * d / np.where(norm > 0, norm, 1.0)
    elif missed.any():
        xy[missed] = np.nan
    return xy


@dataclass(frozen=True, eq=False)
class Undistortion:
    """How the images of one distorted camera map onto its pinhole replacement.

    Attributes
    ----------
    source : Camera
        The distorted camera's pinhole part (its ``fx, fy, cx, cy``, size and pose).
    lens : Lens
    camera : Camera
        The pinhole camera of the undistorted images: same pose and focal lengths,
        the size and principal point of the crop (see the module docstring).
    map_x, map_y : ndarray, shape (H', W'), float32
        Source position of every output pixel centre, in OpenCV's pixel convention (``cv2.remap``).
    valid : ndarray, shape (H', W'), bool
        Output pixels whose source position lies inside the source image.
    """

    source: Camera
    lens: Lens
    camera: Camera
    map_x: np.ndarray
    map_y: np.ndarray
    valid: np.ndarray

    def remap(self, array: np.ndarray, interpolation: int) -> np.ndarray:
        """``array`` (H, W[, C]) of the source camera resampled onto the output camera (H', W'[, C])."""
        return cv2.remap(array, self.map_x, self.map_y, interpolation, borderMode=cv2.BORDER_REPLICATE)

    def image(self, img: np.ndarray) -> np.ndarray:
        """An RGB float32 image (H, W, 3) in [0, 1], undistorted (bicubic, clipped to [0, 1])."""
        out = self.remap(np.ascontiguousarray(img, dtype=np.float32), IMAGE_INTERPOLATION)
        return np.clip(out, 0.0, 1.0)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """A z-depth map (H, W) (``inf`` = no surface), undistorted; the values stay z-depths.

        Undistortion keeps the camera centre and axes, so a surface point has the same z-depth
        in both images; only where it is sampled changes.  Inverse depth is interpolated
        bilinearly (exact on a plane, whose inverse depth is affine in the image) where that
        agrees with the nearest source pixel to :data:`DEPTH_EDGE_TOLERANCE`; elsewhere, at
        depth edges and next to ``inf``, the nearest source pixel's depth is taken, so no
        depth between two surfaces is invented.
        """
        depth = np.ascontiguousarray(depth, dtype=np.float32)
        nearest = self.remap(depth, cv2.INTER_NEAREST)
        with np.errstate(divide="ignore", invalid="ignore"):
            smooth = np.float32(1.0) / self.remap(np.float32(1.0) / depth, cv2.INTER_LINEAR)
            agree = np.abs(smooth - nearest) <= DEPTH_EDGE_TOLERANCE * nearest
        return np.where(agree, smooth, nearest).astype(np.float32)

    def mask(self, mask: np.ndarray) -> np.ndarray:
        """A bool mask (H, W), undistorted by nearest neighbour."""
        return self.remap(np.asarray(mask, np.uint8), cv2.INTER_NEAREST) > 0

    def key(self) -> dict:
        """Everything that decides the output files apart from the source bytes (for the cache key)."""
        s, c = self.source, self.camera
        # Not the model's name: SIMPLE_RADIAL k and OPENCV (k, 0, 0, 0) give the same files.
        return {"lens": [self.lens.fisheye, list(self.lens.coeffs)],
                "source": [s.width, s.height, s.fx, s.fy, s.cx, s.cy],
                "output": [c.width, c.height, c.fx, c.fy, c.cx, c.cy]}


def _crop_interval(lo: float, hi: float, focal: float, size: int, what: str, lens: Lens) -> tuple[int, float]:
    """Output size (pixels) and principal point along one axis for the valid interval [lo, hi] (normalised)."""
    limit = MAX_SCALE * size / focal
    if hi - lo > limit:  # keep the part around the optical axis (normalised 0)
        centre = float(np.clip(0.0, lo + limit / 2, hi - limit / 2))
        lo, hi = centre - limit / 2, centre + limit / 2
    extent = (hi - lo) * focal
    # A thousandth of a pixel of slack, so an undistorted image of zero distortion keeps its size.
    pixels = int(np.floor(extent + 1e-3))
    if not pixels >= MIN_SCALE * size:
        raise NimbusError(f"lens distortion {lens.describe()} leaves an undistorted {what} of {max(extent, 0):.1f} "
                          f"pixels with source data out of {size} (less than {MIN_SCALE:.0%}): the calibration is "
                          "wrong; re-estimate it (e.g. nimbus-synth sfm) or fix the coefficients")
    return pixels, -lo * focal - (extent - pixels) / 2


def plan_undistortion(camera: Camera, lens: Lens) -> Undistortion:
    """The pinhole camera and resampling maps that undistort images of ``camera`` through ``lens``.

    The source image's border (every half pixel) is undistorted; its inner envelope bounds
    the output rectangle (see the module docstring).  Raises NimbusError, saying what to
    fix, when the coefficients cannot be a lens: the border does not map back onto itself
    (the distortion cannot be inverted there), the result would fold over itself, or too
    little of the image would remain.
    """
    w, h = camera.width, camera.height
    xs, ys = np.linspace(0, w, 2 * w + 1), np.linspace(0, h, 2 * h + 1)
    sides = {"left": np.stack([np.zeros_like(ys), ys], 1), "right": np.stack([np.full_like(ys, w), ys], 1),
             "top": np.stack([xs, np.zeros_like(xs)], 1), "bottom": np.stack([xs, np.full_like(xs, h)], 1)}
    xy = {side: undistort_points(px, camera, lens) for side, px in sides.items()}
    if any(np.isnan(v).any() for v in xy.values()):
        raise NimbusError(f"lens distortion {lens.describe()} cannot be inverted at the border of the "
                          f"{w}x{h} image (the coefficients fold the image onto itself there): check the "
                          "calibration (its coefficients and their order) or re-estimate it")
    left, right = float(xy["left"][:, 0].max()), float(xy["right"][:, 0].min())
    top, bottom = float(xy["top"][:, 1].max()), float(xy["bottom"][:, 1].min())
    if not (right > left and bottom > top):
        raise NimbusError(f"lens distortion {lens.describe()} leaves no part of the {w}x{h} image with source data "
                          "after undistortion: the calibration is wrong; re-estimate it or fix the coefficients")
    out_w, out_cx = _crop_interval(left, right, camera.fx, w, "width", lens)
    out_h, out_cy = _crop_interval(top, bottom, camera.fy, h, "height", lens)
    out = Camera(out_w, out_h, camera.fx, camera.fy, out_cx, out_cy, camera.R, camera.t)

    K, K_out, size = opencv_matrix(camera), opencv_matrix(out), (out_w, out_h)
    if lens.fisheye:
        map_x, map_y = cv2.fisheye.initUndistortRectifyMap(K, lens.dist, np.eye(3), K_out, size, cv2.CV_32FC1)
    else:
        map_x, map_y = cv2.initUndistortRectifyMap(K, lens.dist, np.eye(3), K_out, size, cv2.CV_32FC1)
    # A real lens maps left to right and top to bottom; coefficients that do not inside the crop fold it.
    if (np.diff(map_x, axis=1) <= 0).any() or (np.diff(map_y, axis=0) <= 0).any() or \
            not (np.isfinite(map_x).all() and np.isfinite(map_y).all()):
        raise NimbusError(f"lens distortion {lens.describe()} folds the {w}x{h} image onto itself: the "
                          "coefficients cannot be a lens; check the calibration (and the order of its coefficients)")
    tol = ROUND_TRIP_TOLERANCE_PX
    valid = (map_x >= -0.5 - tol) & (map_x <= w - 0.5 + tol) & (map_y >= -0.5 - tol) & (map_y <= h - 0.5 + tol)
    return Undistortion(camera, lens, out, map_x, map_y, valid)


# --- views and the cache -------------------------------------------------------------------------
def default_cache_dir() -> Path:
    """``$NIMBUS_CACHE/undistorted`` (default ``~/.cache/nimbus/undistorted``)."""
    return cache_root() / CACHE_SUBDIR


class _Cache:
    """Content-addressed files of undistorted views in ``folder`` (see the module docstring)."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.new = self.reused = 0

    def get(self, kind: str, suffix: str, source: Path | None, plan: Undistortion,
            make: Callable[[], bytes]) -> Path:
        """The cached file of ``kind`` for ``source`` (None: made from the plan alone), made on a miss."""
        digest = hashlib.sha256()
        try:
            if source is not None:
                with open(source, "rb") as f:
                    while block := f.read(1 << 20):
                        digest.update(block)
        except OSError as e:
            raise NimbusError(f"{kind} {source} cannot be read ({e.strerror}); check the scene's files") from None
        key = json.dumps({"version": UNDISTORT_VERSION, "opencv": cv2.__version__, "kind": kind,
                          "source_sha256": digest.hexdigest() if source is not None else None, **plan.key()},
                         sort_keys=True)
        path = self.folder / hashlib.sha256(key.encode()).hexdigest() / f"{kind}{suffix}"
        if path.is_file():
            self.reused += 1
            return path
        data = make()
        try:
            atomic_write_bytes(path, data)
        except OSError as e:
            raise NimbusError(f"cannot write the undistortion cache {self.folder} ({e.strerror or e}); set "
                              "NIMBUS_CACHE to a writable folder, or undistort the scene once with "
                              "`nimbus-synth undistort SCENE --out DIR` and load DIR") from None
        self.new += 1
        return path


def _depth_bytes(depth: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, np.asarray(depth, dtype=np.float32), allow_pickle=False)
    return buf.getvalue()


def _mask_png(mask: np.ndarray) -> bytes:
    return encode_png(np.where(mask, 255, 0).astype(np.uint8))


def undistort_view(view: View, plan: Undistortion, cache: _Cache) -> View:
    """``view`` with the plan's pinhole camera and its files undistorted into ``cache``."""
    if any(a is not None for a in (view.image, view.depth, view.mask, view.sky)) or view.image_path is None:
        raise ValueError("undistort_view takes views read from files (image_path set, no in-memory arrays)")
    changes: dict = {"camera": plan.camera}
    changes["image_path"] = cache.get("image", ".png", view.image_path, plan,
                                      lambda: encode_png(plan.image(view.load_image())))
    if view.depth_path is not None:
        changes["depth_path"] = cache.get("depth", ".npy", view.depth_path, plan,
                                          lambda: _depth_bytes(plan.depth(view.load_depth())))
    if view.sky_path is not None:
        changes["sky_path"] = cache.get("sky", ".png", view.sky_path, plan,
                                        lambda: _mask_png(plan.mask(view.load_sky())))
    if view.mask_path is not None:
        changes["mask_path"] = cache.get("mask", ".png", view.mask_path, plan,
                                         lambda: _mask_png(plan.mask(view.load_mask()) & plan.valid))
    elif not plan.valid.all():
        changes["mask_path"] = cache.get("valid", ".png", None, plan, lambda: _mask_png(plan.valid))
    return replace(view, **changes)


def undistort_views(views: Sequence[View], lenses: Sequence[Lens | None], cache_dir: str | os.PathLike | None = None,
                    where: str = "") -> tuple[list[View], dict | None]:
    """Replace every view that has a lens by its undistorted pinhole view; log one notice line.

    Parameters
    ----------
    views : sequence of View
        Views read from files (paths, no in-memory arrays), with the distorted cameras' pinhole part.
    lenses : sequence of Lens or None
        Each view's lens; None (or a lens without distortion) leaves the view as it is.
    cache_dir : path, optional
        Where the undistorted files go (default :func:`default_cache_dir`).  Never inside the input.
    where : str
        The scene, for the notice.

    Returns
    -------
    views : list of View
    info : dict or None
        For the scene's metadata: views undistorted, the lenses, the cache folder,
        :data:`UNDISTORT_VERSION`; None when no view has distortion.
    """
    if len(views) != len(lenses):
        raise ValueError(f"{len(views)} views but {len(lenses)} lenses")
    todo = [i for i, lens in enumerate(lenses) if lens is not None and not lens.is_identity]
    if not todo:
        return list(views), None
    cache = _Cache(Path(cache_dir) if cache_dir is not None else default_cache_dir())
    plans: dict[tuple, Undistortion] = {}
    out = list(views)
    sizes: Counter = Counter()
    for i in todo:
        v, lens = views[i], lenses[i]
        c = v.camera
        key = (c.width, c.height, c.fx, c.fy, c.cx, c.cy, lens)
        if key not in plans:
            try:
                plans[key] = plan_undistortion(Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy), lens)
            except NimbusError as e:
                raise NimbusError(f"{where + ': ' if where else ''}view {v.name}: {e}") from None
        plan = plans[key]
        # The plan is per intrinsics; the pose is the view's own.
        out[i] = undistort_view(v, replace(plan, camera=plan.camera.with_pose(c.R, c.t)), cache)
        sizes[f"{c.width}x{c.height} -> {plan.camera.width}x{plan.camera.height}"] += 1
    described = sorted({lenses[i].describe() for i in todo})
    invalid = sum(1 for p in plans.values() if not p.valid.all())
    log.warning("%sundistorted %d view(s) with lens distortion %s to pinhole cameras (%s)%s; cache %s "
                "(%d file(s) new, %d reused)", f"{where}: " if where else "", len(todo), "; ".join(described[:3])
                + (f" and {len(described) - 3} more" if len(described) > 3 else ""),
                ", ".join(sizes), f", {invalid} camera(s) with invalid border pixels masked" if invalid else "",
                cache.folder, cache.new, cache.reused)
    info = {"views": len(todo), "lenses": described, "cache": str(cache.folder), "version": UNDISTORT_VERSION}
    return out, info
