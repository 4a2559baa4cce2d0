"""Per-view depth for the synthesizer: from the scene, a quick 3DGS fit, sparse SfM points or an ONNX model.

Every source returns a z-depth map, float32 (H, W), in scene units, with
``inf`` where there is no surface (sky, backdrop).  Sources (``--depth``):

``scene``
    The views' own depth maps (built-in scenes; user ``depths/<stem>.npy`` or
    16-bit PNG files, see :meth:`nimbus.data.scene.View.load_depth`).
``sparse``
    The scene's sparse points projected into the view (nearest point per pixel,
    points hidden behind nearer ones dropped), densified in inverse depth by a
    push-pull pyramid fill, then refined edge-aware with a guided filter
    (:func:`nimbus.utils.guided.guided_filter`) guided by the image.  Inverse depth is
    interpolated because it is what varies linearly across a planar surface in
    the image.  Without a mask, sky pixels get the depth of the nearest points
    (SfM has no points there): give sky masks (``sky/``) or use ``onnx``.
``onnx:MODEL.onnx``
    A monocular relative inverse-depth network (Depth-Anything-v2 style: NCHW
    float input normalised with the ImageNet mean / std, sides multiples of 14)
    run with onnxruntime, then aligned per view to the inverse depths of the
    sparse points seen by the view with a robust scale + shift
    (:func:`align_inverse_depth`: the 3DGS median / MAD estimate, refined by
    Huber IRLS least squares).
``recon``
    A quick 3DGS fit to all the (clean) views, whose rendered expected depth is
    each view's depth (:mod:`nimbus.train.depth_recon`): one model for every
    view, so the maps are multi-view consistent by construction.  Cached by
    content in :attr:`DepthConfig.recon_cache` (default: the user cache folder,
    ``$NIMBUS_CACHE/depth``; ``degrade --depth-cache``).
``auto``
    The best source the scene allows (:func:`pick_depth_source`): ``scene`` when
    every view has a depth map, else ``onnx`` when a model is configured
    (:attr:`DepthConfig.model`), else ``recon``, else ``sparse`` (a scene with
    too few views to fit).

:mod:`weather_synth.depth_consistency` measures how well the maps of
neighbouring views agree.

Views with a mask (True = backdrop / sky) get ``inf`` depth there when
:attr:`DepthConfig.backdrop_at_infinity` is set: the sky is infinitely far, so
haze covers it with pure airlight as a real atmosphere does.
"""

from __future__ import annotations

import functools
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, ClassVar

import cv2
import numpy as np

from nimbus.config_validation import Limit, at_least, between, fraction, one_of, positive
from nimbus.data.camera import Camera
from nimbus.data.scene import Scene, View
from nimbus.errors import NimbusError
from nimbus.utils.fs import cache_root
from nimbus.utils.guided import guided_filter
from nimbus.utils.onnx_session import open_image_model

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
ALIGN_METHODS = ("mad", "huber")
# Huber threshold in robust standard deviations (95 % efficiency under Gaussian noise).
HUBER_K = 1.345
# MAD -> standard deviation for Gaussian data.
MAD_TO_STD = 1.4826
#: Source kinds (``onnx`` is written ``onnx:MODEL.onnx``).
DEPTH_SOURCES = ("auto", "scene", "recon", "sparse", "onnx")


@dataclass(frozen=True)
class DepthConfig:
    """How depth is obtained (see the module docstring).

    Attributes
    ----------
    source : str
        ``"scene"``, ``"sparse"``, ``"recon"``, ``"onnx:PATH"`` or ``"auto"``.
    backdrop_at_infinity : bool
        Masked (backdrop / sky) pixels get infinite depth.
    min_points : int
        sparse / onnx: fewest sparse points a view must see.
    occlusion_window : float
        sparse / onnx: a projected point is dropped when a point nearer by more
        than ``occlusion_tolerance`` (relative) lies within this window
        (fraction of the image width).
    occlusion_tolerance : float
        Relative depth margin of that test.
    guided_radius : float
        sparse: guided-filter radius as a fraction of the image width.
    guided_eps : float
        sparse: guided-filter regularisation (on inverse depth normalised to [0, 1]).
    input_size : int
        onnx: shorter input side for models with dynamic input size (rounded to a multiple of 14).
    align : str
        onnx: ``"huber"`` (median / MAD start, Huber IRLS) or ``"mad"`` (3DGS's estimate only).
    model : str
        auto: the ONNX model to use when the scene has no depth maps ("": none, so ``recon``).
    recon_preset, recon_iterations, recon_min_alpha :
        recon: the fit's schedule and length, and the opacity below which a
        pixel is sky (:class:`nimbus.train.depth_recon.ReconDepthConfig`).
    recon_cache : str
        recon: folder of the fit cache; "" (default): :func:`default_depth_cache`;
        "none": fit every time.  A machine path, not a property of the result:
        left out of the manifest.
    """

    source: str = "scene"
    backdrop_at_infinity: bool = True
    min_points: int = 8
    occlusion_window: float = 0.015
    occlusion_tolerance: float = 0.1
    guided_radius: float = 0.03
    guided_eps: float = 1e-3
    input_size: int = 518
    align: str = "huber"
    model: str = ""
    recon_preset: str = "tiny"
    recon_iterations: int = 600
    recon_min_alpha: float = 0.5
    recon_cache: str = ""

    #: The accepted values of each field (see :mod:`nimbus.config_validation`).
    LIMITS: ClassVar[dict[str, Limit]] = {
        "align": one_of(*ALIGN_METHODS),
        "min_points": at_least(2), "occlusion_window": fraction(note="of the image width"),
        "occlusion_tolerance": at_least(0), "guided_radius": fraction(note="of the image width"),
        "guided_eps": positive(), "input_size": at_least(14, note="pixels"),
        "recon_iterations": at_least(2), "recon_min_alpha": between(0, 1, lo_open=True, hi_open=True),
    }

    def __post_init__(self) -> None:
        kind = self.source.split(":", 1)[0]
        if kind not in DEPTH_SOURCES or (kind == "onnx") != (":" in self.source):
            raise NimbusError(f"unknown depth source {self.source!r}; use auto, scene, recon, sparse or "
                              "onnx:MODEL.onnx")
        if self.align not in ALIGN_METHODS:
            raise NimbusError(f"unknown depth alignment {self.align!r}; use one of {ALIGN_METHODS}")
        if self.min_points < 2:
            raise NimbusError(f"min_points must be >= 2, got {self.min_points}")


# --- small helpers ------------------------------------------------------------------------
def default_depth_cache() -> Path:
    """Where ``nimbus-synth degrade`` caches recon fits: ``$NIMBUS_CACHE/depth``, else ``~/.cache/nimbus/depth``.

    The same cache root as the LPIPS weights and undistorted images
    (:func:`nimbus.utils.fs.cache_root`).  A per-user cache, not an output: the
    files are named by content, so any run of any scene may reuse them.
    """
    return cache_root() / "depth"


def sanitize_depth(depth: np.ndarray) -> np.ndarray:
    """float32 depth with NaN and negative values read as "no surface" (``inf``); 0 and ``inf`` kept."""
    d = np.asarray(depth, dtype=np.float32)
    bad = np.isnan(d) | (d < 0)
    return np.where(bad, np.float32(np.inf), d) if bad.any() else d


@functools.lru_cache(maxsize=16)
def _ray_norm(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    cam = Camera(width, height, fx, fy, cx, cy)
    n = np.linalg.norm(cam.pixel_rays(np.float64), axis=-1)
    n.setflags(write=False)
    return n


def ray_norm(camera: Camera) -> np.ndarray:
    """``|(x', y', 1)|`` per pixel (H, W), float64: ray distance = z-depth * ray_norm."""
    return _ray_norm(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)


def _grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(image, dtype=np.float32), cv2.COLOR_RGB2GRAY)


# --- sparse points --------------------------------------------------------------------------
def visible_point_indices(camera: Camera, points: np.ndarray, window: float = 0.015, tolerance: float = 0.1
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sparse points seen by a camera: indices into ``points``, pixel columns, rows and z-depths of the kept points.

    Points behind the camera or outside the image are dropped; per pixel the
    nearest point wins; a point is dropped as occluded when a point nearer by
    more than ``tolerance`` (relative) projects within ``window * width`` pixels.
    Indices are increasing (int64); columns and rows are the pixels the points
    fall in (int64, ``image[v, u]``).
    """
    W, H = camera.width, camera.height
    if len(points) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    uv, z = camera.project(points)
    ok = (z > 1e-9) & np.isfinite(uv).all(1)
    ok &= (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    idx = np.flatnonzero(ok)
    u, v, z = uv[ok, 0].astype(np.int64), uv[ok, 1].astype(np.int64), z[ok]
    # Nearest point per pixel: sort far to near so the nearest write lands last.
    zbuf = np.full((H, W), np.inf, np.float32)
    order = np.argsort(-z, kind="stable")
    zbuf[v[order], u[order]] = z[order]
    keep = zbuf[v, u] == z.astype(np.float32)
    k = max(1, int(round(window * W))) * 2 + 1
    near = cv2.erode(zbuf, np.ones((k, k), np.uint8), borderType=cv2.BORDER_REPLICATE)
    keep &= z <= near[v, u] * (1 + tolerance)
    return idx[keep], u[keep], v[keep], z[keep]


def visible_points(camera: Camera, points: np.ndarray, window: float = 0.015,
                   tolerance: float = 0.1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel columns, rows and z-depths of the sparse points a camera sees (:func:`visible_point_indices`)."""
    _, u, v, z = visible_point_indices(camera, points, window, tolerance)
    return u, v, z


def fill_sparse(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Fill an (H, W) image known where ``weights > 0`` by a push-pull pyramid (smooth, no holes).

    Each coarser level averages the known values (weighted); going back up,
    unknown pixels take the bilinearly upsampled coarser estimate.
    """
    vals = [np.asarray(values, np.float32) * weights]
    wts = [np.asarray(weights, np.float32)]
    while min(wts[-1].shape) > 1 and np.any(wts[-1] == 0):
        h, w = wts[-1].shape
        size = (max(1, (w + 1) // 2), max(1, (h + 1) // 2))
        vals.append(cv2.resize(vals[-1], size, interpolation=cv2.INTER_AREA))
        wts.append(cv2.resize(wts[-1], size, interpolation=cv2.INTER_AREA))
    est = np.where(wts[-1] > 0, vals[-1] / np.maximum(wts[-1], 1e-12), 0).astype(np.float32)
    if not np.any(wts[-1] > 0):
        raise NimbusError("nothing to interpolate: no known depth values")
    if np.any(wts[-1] == 0):
        est[:] = est[wts[-1] > 0].mean()
    for lv in range(len(vals) - 2, -1, -1):
        h, w = wts[lv].shape
        up = cv2.resize(est, (w, h), interpolation=cv2.INTER_LINEAR)
        known = wts[lv] > 0
        est = np.where(known, vals[lv] / np.maximum(wts[lv], 1e-12), up).astype(np.float32)
    return est


def densify_sparse_depth(camera: Camera, points: np.ndarray, image: np.ndarray | None,
                         config: DepthConfig = DepthConfig(), name: str = "view") -> tuple[np.ndarray, dict]:
    """Dense z-depth (H, W) float32 from sparse world points, plus info (points used).

    Raises NimbusError when the view sees fewer than ``config.min_points`` points.
    """
    u, v, z = visible_points(camera, points, config.occlusion_window, config.occlusion_tolerance)
    if len(z) < config.min_points:
        raise NimbusError(f"view {name} sees only {len(z)} sparse points (need {config.min_points}) for "
                          "--depth sparse; use --depth scene (depth maps) or --depth onnx:MODEL.onnx")
    H, W = camera.height, camera.width
    inv = np.zeros((H, W), np.float32)
    wt = np.zeros((H, W), np.float32)
    inv[v, u] = 1.0 / z
    wt[v, u] = 1.0
    dense = fill_sparse(inv, wt)
    lo, hi = float(dense.min()), float(dense.max())
    if image is not None and hi > lo:
        r = max(1, int(round(config.guided_radius * W)))
        norm = ((dense - lo) / (hi - lo)).astype(np.float32)
        refined = guided_filter(_grey(image), norm, r, config.guided_eps)
        dense = np.clip(refined, 0, 1) * (hi - lo) + lo
    with np.errstate(divide="ignore"):
        depth = np.where(dense > 0, 1.0 / dense, np.inf).astype(np.float32)
    return depth, {"sparse_points": int(len(z))}


# --- monocular model -------------------------------------------------------------------------
def align_inverse_depth(mono: np.ndarray, target: np.ndarray, method: str = "huber",
                        iterations: int = 10) -> tuple[float, float]:
    """Robust ``scale, shift`` with ``target ~ scale * mono + shift`` (1-D samples).

    ``"mad"``: the 3DGS estimate ``scale = MAD(target) / MAD(mono)``,
    ``shift = median(target) - scale * median(mono)``.  ``"huber"``: that start
    refined by iteratively reweighted least squares with Huber weights
    (threshold 1.345 robust sigmas), which is exact on noise-free data and
    ignores a minority of outliers.
    """
    x = np.asarray(mono, np.float64).ravel()
    y = np.asarray(target, np.float64).ravel()
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if len(x) < 2:
        raise NimbusError("depth alignment needs at least 2 sparse points with finite values")
    mx, my = np.median(x), np.median(y)
    mad_x, mad_y = np.median(np.abs(x - mx)), np.median(np.abs(y - my))
    if not mad_x > 0:
        raise NimbusError("the depth model's output is constant over the sparse points; it cannot be aligned")
    scale = mad_y / mad_x
    shift = my - scale * mx
    if method == "huber":
        for _ in range(iterations):
            r = y - (scale * x + shift)
            sigma = MAD_TO_STD * np.median(np.abs(r - np.median(r)))
            if sigma <= 1e-12 * max(1.0, np.abs(y).max()):
                # Residuals already (nearly) zero for most points: plain least squares on the inliers.
                w = (np.abs(r) <= 1e-9 * max(1.0, np.abs(y).max())).astype(np.float64)
                if w.sum() < 2:
                    w = np.ones_like(r)
            else:
                a = np.abs(r) / (HUBER_K * sigma)
                w = np.where(a <= 1, 1.0, 1.0 / np.maximum(a, 1e-300))
            A = np.stack([x, np.ones_like(x)], 1) * np.sqrt(w)[:, None]
            sol, *_ = np.linalg.lstsq(A, y * np.sqrt(w), rcond=None)
            if np.allclose(sol, (scale, shift), rtol=1e-12, atol=1e-15):
                scale, shift = float(sol[0]), float(sol[1])
                break
            scale, shift = float(sol[0]), float(sol[1])
    return float(scale), float(shift)


class OnnxDepthModel:
    """A relative inverse-depth ONNX model run with onnxruntime on CPU.

    Input: NCHW float32, ImageNet-normalised RGB; output: (1, H', W') or
    (1, 1, H', W') relative inverse depth (larger = nearer), resized back to the image.
    """

    def __init__(self, path: str | Path, input_size: int = 518) -> None:
        model = open_image_model(path, "depth model", "give --depth onnx:PATH/TO/MODEL.onnx",
                                 "export it with opset >= 11")
        self.session, self.input_name, self.fixed_size, self.path = (model.session, model.input_name,
                                                                     model.fixed_size, model.path)
        self.input_size = int(input_size)

    def input_resolution(self, width: int, height: int) -> tuple[int, int]:
        """(width, height) fed to the model: its fixed size, or the short side ~ input_size, multiples of 14."""
        if self.fixed_size is not None:
            return self.fixed_size
        s = self.input_size / min(width, height)
        return (max(14, int(round(width * s / 14)) * 14), max(14, int(round(height * s / 14)) * 14))

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """Relative inverse depth (H, W), float32, for an RGB image (H, W, 3) in [0, 1]."""
        H, W = image.shape[:2]
        w, h = self.input_resolution(W, H)
        x = image if (w, h) == (W, H) else cv2.resize(image, (w, h), interpolation=cv2.INTER_CUBIC)
        x = ((np.asarray(x, np.float32) - IMAGENET_MEAN) / IMAGENET_STD).transpose(2, 0, 1)[None]
        out = self.session.run(None, {self.input_name: np.ascontiguousarray(x, dtype=np.float32)})[0]
        out = np.squeeze(np.asarray(out, np.float32))
        if out.ndim != 2:
            raise NimbusError(f"depth model {self.path} returned shape {np.shape(out)}; expected (1, [1,] H, W)")
        if out.shape != (H, W):
            out = cv2.resize(out, (W, H), interpolation=cv2.INTER_LINEAR)
        return out


def onnx_depth(model: OnnxDepthModel, camera: Camera, image: np.ndarray, points: np.ndarray,
               config: DepthConfig = DepthConfig(), name: str = "view") -> tuple[np.ndarray, dict]:
    """Monocular inverse depth aligned to the view's sparse points; z-depth (H, W) float32 and info."""
    mono = model(image)
    u, v, z = visible_points(camera, points, config.occlusion_window, config.occlusion_tolerance)
    if len(z) < config.min_points:
        raise NimbusError(f"view {name} sees only {len(z)} sparse points (need {config.min_points}) to align "
                          "the depth model's scale; the scene needs SfM points (sparse/0/points3D)")
    scale, shift = align_inverse_depth(mono[v, u], 1.0 / z, config.align)
    if not scale > 0:
        raise NimbusError(f"depth model {model.path} output decreases with inverse depth in view {name} "
                          f"(fitted scale {scale:.3g}); it must predict relative INVERSE depth (disparity)")
    inv = scale * mono.astype(np.float64) + shift
    with np.errstate(divide="ignore"):
        depth = np.where(inv > 0, 1.0 / inv, np.inf).astype(np.float32)
    return depth, {"sparse_points": int(len(z)), "align_scale": scale, "align_shift": shift}


# --- the source used by the synthesizer -------------------------------------------------------
def _recon():
    """:mod:`nimbus.train.depth_recon`, imported here only.

    weather_synth imports nothing of nimbus but ``nimbus.data`` (and the shared
    errors and file helpers); ``recon`` is the one deliberate exception: the
    depth comes from the project's own 3DGS trainer.  The import is lazy so that
    the other sources never load the trainer (nor torch).
    """
    from nimbus.train import depth_recon

    return depth_recon


def recon_config(config: DepthConfig):
    """The :class:`nimbus.train.depth_recon.ReconDepthConfig` a depth config describes."""
    return _recon().ReconDepthConfig(preset=config.recon_preset, iterations=config.recon_iterations,
                                     min_alpha=config.recon_min_alpha)


def pick_depth_source(scene: Scene, config: DepthConfig = DepthConfig()) -> tuple[str, str]:
    """The source ``auto`` stands for on ``scene``, and why (one line).

    In order of preference: the scene's own depth maps (exact); a configured ONNX
    model (:attr:`DepthConfig.model`: per-view, but learned on real photos);
    ``recon`` (a 3DGS fit: consistent across views); ``sparse`` (view by view
    between the SfM points; only when the scene has too few views to fit).
    """
    views = scene.views
    if views and all(v.has_depth for v in views):
        return "scene", "every view has a depth map"
    lacking = "no view has a depth map" if not any(v.has_depth for v in views) else \
        f"{sum(not v.has_depth for v in views)} of {len(views)} views have no depth map"
    if config.model:
        return f"onnx:{config.model}", f"{lacking}; an ONNX depth model is configured"
    min_views = _recon().MIN_RECON_VIEWS
    if len(views) >= min_views:
        return "recon", f"{lacking}; no ONNX model configured (depth.model), so a 3DGS fit to the views"
    if len(scene.points) >= config.min_points:
        return "sparse", f"{lacking}; {len(views)} views are too few to fit 3DGS (need {min_views}), so the " \
                         "densified sparse points"
    raise NimbusError(f"no depth for haze: {lacking}, the scene has {len(views)} views (a 3DGS fit needs "
                      f"{min_views}) and {len(scene.points)} sparse points (need {config.min_points}); add "
                      "depths/<name>.npy or give --depth onnx:MODEL.onnx")


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


class DepthSource:
    """Gives each view's z-depth map according to a :class:`DepthConfig` (see the module docstring).

    ``source="auto"`` is resolved here (:func:`pick_depth_source`); the choice is
    printed as one line to ``log`` and recorded by :meth:`describe`.  ``recon``
    fits at construction (so a scene it cannot fit fails before anything is
    written), printing its progress to ``log``.
    """

    def __init__(self, scene: Scene, config: DepthConfig = DepthConfig(),
                 log: Callable[[str], None] | None = _stderr) -> None:
        self.scene = scene
        self.config = config
        self.log = log or (lambda line: None)
        self.requested = config.source
        self.reason = ""
        source = config.source
        if source == "auto":
            source, self.reason = pick_depth_source(scene, config)
            self.log(f"depth: auto picked {source} ({self.reason})")
        self.source = source
        self.kind = source.split(":", 1)[0]
        self.model = None
        self.recon = None
        if self.kind == "scene":
            missing = [v.name for v in scene.views if not v.has_depth]
            if missing:
                raise NimbusError(f"{len(missing)} view(s) have no depth map (e.g. {missing[0]}); add "
                                  "depths/<name>.npy to the scene or use --depth auto (picks one), --depth recon, "
                                  "--depth sparse or --depth onnx:MODEL.onnx")
        elif self.kind == "recon":
            cache = None if config.recon_cache == "none" else (config.recon_cache or default_depth_cache())
            self.recon = _recon().recon_depth(scene, recon_config(config), cache, self.log)
        elif len(scene.points) < config.min_points:
            raise NimbusError(f"--depth {self.kind} needs the scene's sparse points, but it has {len(scene.points)}; "
                              "use a COLMAP scene with points3D, --depth recon or --depth scene")
        if self.kind == "onnx":
            self.model = OnnxDepthModel(source.split(":", 1)[1], config.input_size)

    def __call__(self, view: View, image: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
        """z-depth (H, W) float32 (inf = no surface) and per-view info for the manifest."""
        if self.kind == "scene":
            depth, info = view.load_depth(), {}
            if depth.shape != (view.camera.height, view.camera.width):
                raise NimbusError(f"depth map of view {view.name} has shape {depth.shape}; its camera is "
                                  f"{view.camera.width}x{view.camera.height}")
        elif self.kind == "recon":
            if view.name not in self.recon.depths:
                raise NimbusError(f"view {view.name} was not part of the recon depth fit; degrade the scene the "
                                  "depth source was built for")
            depth, info = self.recon.depths[view.name], {}
        else:
            image = view.load_image() if image is None else image
            if self.kind == "sparse":
                depth, info = densify_sparse_depth(view.camera, self.scene.points, image, self.config, view.name)
            else:
                depth, info = onnx_depth(self.model, view.camera, image, self.scene.points, self.config, view.name)
        depth = sanitize_depth(depth)
        if self.config.backdrop_at_infinity:
            sky = view.load_sky()
            if sky is not None:
                depth = np.where(sky, np.float32(np.inf), depth)
        return depth, info

    def describe(self) -> dict:
        """The source for the manifest: what was asked, what ran (and why, for ``auto``), its settings."""
        config = {k: v for k, v in vars(self.config).items() if k != "recon_cache"}
        d = {"source": self.source, "config": config}
        if self.requested != self.source:
            d.update(requested=self.requested, reason=self.reason)
        if self.model is not None:
            from nimbus.utils.fs import sha256_file

            d["model_sha256"] = sha256_file(self.model.path)
        if self.recon is not None:
            # Not the time nor whether it came from the cache: a cached run writes the same manifest.
            d["recon"] = {k: v for k, v in self.recon.info.items() if k not in ("cached", "fit_seconds")}
        return d


def depth_scale(scene: Scene, source: DepthSource, max_views: int = 4) -> float:
    """The scene's depth scale: median finite surface ray distance over a few evenly spaced views.

    Physical haze and particle depths are expressed in this unit so that
    defaults suit any scene whatever its (arbitrary) COLMAP units.
    """
    views = scene.views
    if not views:
        raise NimbusError("the scene has no views")
    idx = np.unique(np.linspace(0, len(views) - 1, min(max_views, len(views))).round().astype(int))
    dists = []
    for i in idx:
        v = views[i]
        if source.kind in ("scene", "recon"):  # dense maps: every surface pixel counts
            d, _ = source(v)
            r = d.astype(np.float64) * ray_norm(v.camera)
            dists.append(r[np.isfinite(r) & (r > 0)])
        else:
            u, vv, z = visible_points(v.camera, scene.points)
            dists.append(z * ray_norm(v.camera)[vv, u])
    allr = np.concatenate(dists) if dists else np.zeros(0)
    return float(np.median(allr)) if allr.size else 1.0

