"""Particulate Layer Modelling (PLM): per-view residuals R = ReLU(I_in - I_con), stored compactly.

After stage 1 the continuous-medium render I_con holds the view-consistent scene; what
the input has in excess of it (rain streaks, snow flakes) is the view's particulate layer
R.  Stage 2 renders ``I_deg = I_con + R`` and re-extracts R every Z_ref iterations
(:func:`is_refresh_step`).  R has no learnable parameters.

Which residual becomes R (:func:`particle_mask`).  The paper takes all of
``ReLU(I_in - I_con)``, relying on a 4k-iteration stage 1 that already holds the static
detail.  Pixels absorbed by R give the Gaussians no gradient, so on a short schedule
that would freeze every detail stage 1 has not learned yet (small bright flowers look
like snow to a per-pixel test).  By default R keeps only residuals that are

* outliers of the view's high-passed residual (``outlier_sigmas`` robust standard
  deviations), and
* view-inconsistent (:func:`consistency_excess`): brighter than the same surface point,
  reprojected with the rendered depth, looks in the neighbouring training views (the
  brightest pixel of a 3 x 3 window there, so a one-pixel reprojection error does not
  count as inconsistency).  Pixels without a usable neighbour (sky, occlusion, out of
  view) fall back to the outlier test alone.

``outlier_sigmas = 0`` with no consistency check is the paper's R.

A bound from the input alone (:func:`white_tophat`).  R is refreshed from the current
render, so a pixel whose render has gone too dark (a hole where Gaussians were pruned, a
patch of sky) would have the gap absorbed by R at the next refresh and then never get
a gradient to close it: R feeds its own errors.  Particles are *small* bright
structures (flakes, streaks a few pixels wide), so R is also capped by the input's
white top-hat ``I_in - opening(I_in)`` with a structuring element ``tophat`` of the
image width: on the synthesizer's small garden (snow / rain, 7 px at 240 px) the
top-hat holds 93 % / 88 % of the true particle energy, while a hole or a sky patch
wider than the element has a top-hat near 0 and keeps its gradient.

Storage: one ``uint8`` ``[H, W, 3]`` tensor per training view (R is in [0, 1]; 8-bit
steps of 1/255 are below what a PNG input resolves), replaced in place at each refresh,
so memory is ``3 H W`` bytes per view whatever the run length.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from nimbus.data.camera import Camera
from nimbus.kernels import consistency as consistency_kernel
from nimbus.methods.nimbusgs.ggs import lower_median

_LEVELS = 255.0
_MAD_TO_STD = 1.4826
#: Window of the local mean removed before outliers are looked for (pixels).
HIGHPASS_WINDOW = 5
#: Floor of the robust noise level (intensity units), so a perfect fit does not flag everything.
MIN_SIGMA = 1e-3
#: Window of the maximum filter applied to a neighbour before comparing (pixels): tolerates
#: a reprojection error of one pixel.
CONSISTENCY_WINDOW = 3
#: A reprojected point is occluded in a neighbour when it lies this fraction behind the
#: neighbour's rendered surface.
OCCLUSION_TOLERANCE = 0.05
#: A residual is a particle when at least this fraction of it is view-inconsistent excess.
INCONSISTENT_FRACTION = 0.5


def highpass(x: Tensor, window: int = HIGHPASS_WINDOW) -> Tensor:
    """``x - box_mean(x)`` for a map ``[H, W]`` (replicate padding)."""
    pad = window // 2
    m = F.avg_pool2d(F.pad(x[None, None], (pad, pad, pad, pad), mode="replicate"), window, stride=1)[0, 0]
    return x - m


def tophat_window(width: int, fraction: float) -> int:
    """Odd structuring-element size (pixels, >= 3) for a top-hat of ``fraction`` of ``width``; 0 when off."""
    if fraction <= 0:
        return 0
    k = max(int(round(fraction * width)), 3)
    return k if k % 2 else k + 1


def white_tophat(image: Tensor, window: int) -> Tensor:
    """``image - opening(image)`` per channel of ``[H, W, C]``, square ``window`` (odd, pixels).

    Bright structures narrower than the window survive; smooth regions and anything wider
    go to 0.  Opening = dilation of the erosion; borders are padded so they are not
    mistaken for dark surroundings.
    """
    x = image.float().permute(2, 0, 1)[None]
    opened = _square_max(-_square_max(-x, window), window)  # the dilation of the erosion
    return (x - opened).clamp_min(0.0)[0].permute(1, 2, 0)


def _square_max(x: Tensor, window: int) -> Tensor:
    """The maximum over each ``window`` x ``window`` square of ``x`` [1, C, H, W], borders replicated: as a
    column pass then a row pass over the padded image (the same values as one square pool, a maximum of maxima,
    in 2 ``window`` comparisons a pixel instead of ``window`` squared)."""
    pad = window // 2
    padded = F.pad(x, (pad, pad, pad, pad), mode="replicate")
    return F.max_pool2d(F.max_pool2d(padded, (window, 1), stride=1), (1, window), stride=1)


def _dilate(mask: Tensor) -> Tensor:
    return F.max_pool2d(mask.float()[None, None], 3, stride=1, padding=1)[0, 0] > 0


def outlier_core(image: Tensor, composite: Tensor, sigmas: float) -> Tensor:
    """Pixels ``[H, W]`` whose high-passed residual (mean over RGB) exceeds ``sigmas`` robust standard deviations."""
    d = highpass((image - composite).float().mean(dim=-1))
    flat = d.reshape(-1)  # the medians by selection (lower_median: torch's median, the same element, faster)
    sigma = max(_MAD_TO_STD * float(lower_median((flat - lower_median(flat)).abs())), MIN_SIGMA)
    return d > sigmas * sigma


@dataclass
class ViewGeometry:
    """A training view's rendered surface: ``depth`` [H, W] camera z (depth / alpha), ``valid`` where alpha is high."""

    camera: Camera
    depth: Tensor
    valid: Tensor


def neighbours(cameras: list[Camera], count: int) -> list[list[int]]:
    """For each camera, the ``count`` other cameras with the nearest centres."""
    centers = np.stack([c.center for c in cameras]) if cameras else np.zeros((0, 3))
    out = []
    for i in range(len(cameras)):
        d = np.linalg.norm(centers - centers[i], axis=1)
        d[i] = np.inf
        out.append([int(j) for j in np.argsort(d, kind="stable")[:count] if np.isfinite(d[j])])
    return out


def _rotate(points: Tensor, M: Tensor) -> Tensor:
    """``points @ M`` for ``[..., 3]`` row vectors (``M`` [..., 3, 3], broadcast) as three broadcast products
    summed left to right: a batch of views gives each point the same arithmetic as one view (and the
    same sums as the ``mm`` it replaces, bit for bit on the CPUs checked, so the residuals did not move)."""
    return points[..., :1] * M[..., 0, :] + points[..., 1:2] * M[..., 1, :] + points[..., 2:3] * M[..., 2, :]


def _project(points: Tensor, camera: Camera, R: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
    """Pixel positions ``[M, 2]`` and camera z ``[M]`` of world ``points`` in ``camera`` (rotation ``R``,
    translation ``t``: its pose as tensors of the points' dtype)."""
    p = _rotate(points, R.T) + t
    z = p[:, 2]
    zs = z.clamp_min(1e-9)
    uv = torch.stack([camera.fx * p[:, 0] / zs + camera.cx, camera.fy * p[:, 1] / zs + camera.cy], dim=-1)
    return uv, z


def _sample(image: Tensor, uv: Tensor, mode: str) -> Tensor:
    h, w = image.shape
    grid = torch.stack([uv[:, 0] / w * 2 - 1, uv[:, 1] / h * 2 - 1], dim=-1).reshape(1, 1, -1, 2)
    return F.grid_sample(image[None, None], grid.to(image.dtype), mode=mode, padding_mode="border",
                         align_corners=False).reshape(-1)


@dataclass
class _ViewConstants:
    """What the consistency check needs of a view besides its rendered surface: fixed for a training run."""

    rays: Tensor    # [H * W, 3] float32 camera-frame pixel rays (z = 1)
    R: Tensor       # [3, 3] float32
    t: Tensor       # [3] float32
    bright: Tensor  # [H, W] intensity (mean over RGB), CONSISTENCY_WINDOW-maximum-filtered
    lum: Tensor     # [H, W] intensity (mean over RGB)
    pose: Tensor    # [12] float32: R row-major, then t (the compiled kernel's form)
    intrinsics: Tensor  # [4] float32: fx, fy, cx, cy


def _view_constants(camera: Camera, image: Tensor) -> _ViewConstants:
    device = image.device
    lum = image.float().mean(dim=-1)
    pad = CONSISTENCY_WINDOW // 2
    R = torch.as_tensor(np.array(camera.R), dtype=torch.float32, device=device)
    t = torch.as_tensor(np.array(camera.t), dtype=torch.float32, device=device)
    return _ViewConstants(
        rays=torch.as_tensor(camera.pixel_rays(np.float64), dtype=torch.float32, device=device).reshape(-1, 3),
        R=R, t=t, bright=F.max_pool2d(lum[None, None], CONSISTENCY_WINDOW, stride=1, padding=pad)[0, 0].contiguous(),
        lum=lum, pose=torch.cat([R.reshape(9), t.reshape(3)]),
        intrinsics=torch.tensor([camera.fx, camera.fy, camera.cx, camera.cy], dtype=torch.float32, device=device))


def _excess(image: Tensor, g: ViewGeometry, own: _ViewConstants,
            others: list[tuple[ViewGeometry, _ViewConstants]]) -> Tensor:
    """:func:`consistency_excess` of the view showing ``image`` from its constants and its neighbours':
    by the compiled kernel where it builds (:mod:`nimbus.kernels.consistency`: the same bits as
    :func:`_excess_torch` where torch runs its AVX2 or AVX-512 kernels), else by :func:`_excess_torch`."""
    if others and consistency_kernel.usable(image, g.depth, neighbours=len(others)):
        nbs = [(cj.pose, cj.intrinsics, gj.depth, gj.valid, cj.bright, (gj.camera.width, gj.camera.height))
               for gj, cj in others]
        return consistency_kernel.consistency_excess(own.lum, own.rays, g.depth, g.valid, own.pose,
                                                     nbs).reshape(own.lum.shape)
    return _excess_torch(image, g, own, others)


def _excess_torch(image: Tensor, g: ViewGeometry, own: _ViewConstants,
                  others: list[tuple[ViewGeometry, _ViewConstants]]) -> Tensor:
    """:func:`_excess` in torch ops (the reference the kernel is tested against)."""
    lum = image.float().mean(dim=-1)
    h, w = lum.shape
    p_cam = own.rays * g.depth.reshape(-1, 1).float()
    world = _rotate(p_cam - own.t, own.R)  # R^T (p - t), row vectors
    samples = []
    for gj, cj in others:
        uv, z = _project(world, gj.camera, cj.R, cj.t)
        wj, hj = gj.camera.width, gj.camera.height
        ok = g.valid.reshape(-1) & (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] < wj) & (uv[:, 1] >= 0) & (uv[:, 1] < hj)
        surface = _sample(gj.depth.float(), uv, "nearest")
        seen = _sample(gj.valid.float(), uv, "nearest") > 0
        ok &= seen & (z <= surface * (1 + OCCLUSION_TOLERANCE))
        samples.append(torch.where(ok, _sample(cj.bright, uv, "bilinear"), torch.full_like(z, float("nan"))))
    if not samples:
        return torch.full_like(lum, float("nan"))
    med = torch.nanmedian(torch.stack(samples), dim=0).values
    return (lum.reshape(-1) - med).reshape(h, w)


@torch.no_grad()
def consistency_excess(index: int, images: list[Tensor], geometry: list[ViewGeometry], others: list[int]) -> Tensor:
    """How much brighter view ``index`` is than its neighbours see the same points: ``[H, W]``, NaN where unknown.

    Each pixel with a valid rendered surface is lifted to 3D and projected into the
    ``others`` views; a projection counts when it lands inside the image, in front of
    the camera and not behind that view's rendered surface.  The excess is the view's
    intensity (mean over RGB) minus the median, over the counted neighbours, of their
    3 x 3-maximum-filtered intensity there.  (:class:`ViewConsistency` computes the same for
    every view of a training run, keeping what does not change between calls.)
    """
    def constants(i: int) -> _ViewConstants:
        return _view_constants(geometry[i].camera, images[i])

    return _excess(images[index], geometry[index], constants(index), [(geometry[j], constants(j)) for j in others])


class ViewConsistency:
    """:func:`consistency_excess` of each training view against its ``count`` nearest neighbours, for the
    repeated refreshes of one run.

    What does not change between refreshes is computed once, on first use, and kept (about
    20 bytes per pixel per view): the neighbours, each view's pose and pixel-ray tensors, its
    intensity and its maximum-filtered intensity (from the input alone).  :meth:`excesses`
    checks every view at once: the neighbours' samples of a batch of views are taken by one
    ``grid_sample`` per kind over the stacked neighbour maps, and the elementwise arithmetic runs
    on the whole batch, instead of some thirty small ops per view and neighbour.  Each element
    goes through the same float32 operations as in :func:`consistency_excess` (the median is a
    selection), so the result is the same bit for bit.

    Parameters
    ----------
    cameras : list of Camera
        The training views' cameras (the ``camera`` of each :class:`ViewGeometry` passed later).
    images : list of Tensor
        Their inputs ``[H, W, 3]``.
    count : int
        Neighbours per view (:func:`neighbours`).
    """

    #: Views x neighbours x pixels of one batch of :meth:`excesses`: bounds its work tensors
    #: (a dozen of that many 4-byte elements) whatever the number of views.
    BATCH_ELEMENTS = 1 << 21

    def __init__(self, cameras: list[Camera], images: list[Tensor], count: int) -> None:
        self.cameras = cameras
        self.images = images
        self.others = neighbours(cameras, count)
        self._constants: dict[int, _ViewConstants] = {}
        self._stacked: dict[str, Tensor] = {}

    def _view(self, i: int) -> _ViewConstants:
        if i not in self._constants:
            self._constants[i] = _view_constants(self.cameras[i], self.images[i])
        return self._constants[i]

    @torch.no_grad()
    def excess(self, index: int, geometry: list[ViewGeometry]) -> Tensor:
        """:func:`consistency_excess` of view ``index`` with the current rendered surfaces ``geometry``."""
        return _excess(self.images[index], geometry[index], self._view(index),
                       [(geometry[j], self._view(j)) for j in self.others[index]])

    def _batchable(self) -> bool:
        """Whether :meth:`excesses` can stack the views: one image size, at least one neighbour each."""
        sizes = {(c.height, c.width) for c in self.cameras}
        return len(sizes) == 1 and all(self.others)

    def _stack(self) -> dict[str, Tensor]:
        """The per-view constants stacked over the views (kept): ``rays`` [V, H W, 3], ``R`` [V, 3, 3],
        ``t`` [V, 3], ``lum`` [V, H W], ``bright`` [V, 1, H, W] and ``K`` [V, 4] (fx, fy, cx, cy), float32."""
        if not self._stacked:
            views = [_view_constants(c, img) for c, img in zip(self.cameras, self.images)]
            device = views[0].t.device
            self._stacked = {
                "rays": torch.stack([v.rays for v in views]), "R": torch.stack([v.R for v in views]),
                "t": torch.stack([v.t for v in views]),
                "lum": torch.stack([img.float().mean(dim=-1).reshape(-1) for img in self.images]),
                "bright": torch.stack([v.bright for v in views])[:, None],
                "K": torch.tensor([[c.fx, c.fy, c.cx, c.cy] for c in self.cameras], dtype=torch.float32,
                                  device=device)}
        return self._stacked

    @torch.no_grad()
    def excesses(self, geometry: list[ViewGeometry]) -> list[Tensor]:
        """:meth:`excess` of every view, ``[H, W]`` each, with the current rendered surfaces ``geometry``.

        Where the compiled kernel builds, view after view through it (the batch below gives the same bits where
        torch runs its AVX2 or AVX-512 kernels)."""
        kernel = bool(geometry) and consistency_kernel.usable(geometry[0].depth, neighbours=len(self.others[0]))
        if kernel or not self._batchable():
            return [self.excess(i, geometry) for i in range(len(geometry))]
        h, w = geometry[0].depth.shape
        surfaces = torch.stack([torch.stack([g.depth.float(), g.valid.float()]) for g in geometry])
        size = max(1, self.BATCH_ELEMENTS // (len(self.others[0]) * h * w))
        out = []
        for start in range(0, len(geometry), size):
            views = torch.arange(start, min(start + size, len(geometry)), device=surfaces.device)
            out.extend(self._excess_batch(views, surfaces).reshape(-1, h, w).unbind(0))
        return out

    def _excess_batch(self, views: Tensor, surfaces: Tensor) -> Tensor:
        """:func:`_excess` of ``views`` [B] at once, ``[B, H W]``, element for element the same operations
        (``surfaces`` [V, 2, H, W]: every view's depth and valid mask as float)."""
        s = self._stack()
        h, w = surfaces.shape[-2:]
        depth, valid = surfaces[views].reshape(-1, 2, h * w).unbind(1)
        world = _rotate(s["rays"][views] * depth[..., None] - s["t"][views, None], s["R"][views, None])
        others = torch.tensor(self.others, device=surfaces.device)[views]  # [B, K]
        b, k = others.shape
        flat = others.reshape(-1)
        # Each neighbour's rigid transform ([B, K, H W] per coordinate), as _project.
        p = _rotate(world[:, None], s["R"][others].transpose(-1, -2)[:, :, None]) + s["t"][others][:, :, None]
        px, py, z = p.unbind(-1)
        zs = z.clamp_min(1e-9)
        fx, fy, cx, cy = s["K"][others][..., None].unbind(2)
        u = fx * px / zs + cx
        v = fy * py / zs + cy
        ok = (valid[:, None] > 0) & (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        grid = torch.stack([u / w * 2 - 1, v / h * 2 - 1], dim=-1).reshape(b * k, 1, h * w, 2)
        near = F.grid_sample(surfaces[flat], grid, mode="nearest", padding_mode="border",
                             align_corners=False).reshape(b, k, 2, h * w)
        ok &= (near[:, :, 1] > 0) & (z <= near[:, :, 0] * (1 + OCCLUSION_TOLERANCE))
        bright = F.grid_sample(s["bright"][flat], grid, mode="bilinear", padding_mode="border",
                               align_corners=False).reshape(b, k, h * w)
        samples = torch.where(ok, bright, torch.full_like(bright, float("nan")))
        return s["lum"][views] - torch.nanmedian(samples, dim=1).values


def particle_mask(image: Tensor, composite: Tensor, outlier_sigmas: float, excess: Tensor | None = None,
                  outlier_scope: str = "all") -> Tensor:
    """Where the residual is taken into R ``[H, W]`` bool (module docstring), grown by one pixel.

    ``outlier_scope``: ``all`` applies the outlier test to every pixel (and the consistency
    test where it is known); ``unchecked`` applies it only where the consistency test has no
    neighbour, and lets the consistency test alone decide elsewhere (faint particles, below
    the outlier threshold, still enter R).
    """
    core = outlier_core(image, composite, outlier_sigmas)
    if excess is not None:
        r = (image - composite).float().mean(dim=-1)
        unknown = torch.isnan(excess)
        inconsistent = excess >= INCONSISTENT_FRACTION * r
        if outlier_scope == "unchecked":
            core = torch.where(unknown, core, inconsistent & (r > 0))
        else:
            core &= unknown | inconsistent
    return _dilate(core)


def extract_residual(image: Tensor, composite: Tensor, outlier_sigmas: float = 0.0,
                     excess: Tensor | None = None, bound: Tensor | None = None,
                     outlier_scope: str = "all") -> Tensor:
    """R = ReLU(I_in - I_con), clipped to [0, 1], ``[H, W, 3]`` float; masked by :func:`particle_mask` when
    ``outlier_sigmas > 0`` (``excess``: the view's :func:`consistency_excess`, or None to skip that test)
    and capped by ``bound`` (the input's :func:`white_tophat`) when given."""
    r = (image - composite).clamp(0.0, 1.0)
    if bound is not None:
        r = torch.minimum(r, bound.to(r))
    if outlier_sigmas > 0:
        r = r * particle_mask(image, composite, outlier_sigmas, excess, outlier_scope)[..., None]
    return r


def is_refresh_step(iteration: int, m_init: int, interval: int) -> bool:
    """Whether ``iteration`` (1-based) ends a refresh period of stage 2 (``j mod Z_ref = 0``, j the stage-2 count)."""
    j = iteration - m_init
    return j > 0 and j % interval == 0


class ResidualStore:
    """One quantised residual per training view.

    Parameters
    ----------
    shapes : list of (H, W)
        Image size of each view.
    device : torch.device
    """

    def __init__(self, shapes: list[tuple[int, int]], device=None) -> None:
        self.shapes = [tuple(s) for s in shapes]
        self.device = device
        self.data: list[Tensor] = [torch.zeros((h, w, 3), dtype=torch.uint8, device=device) for h, w in self.shapes]
        #: Iteration at which each view's residual was last written (-1: never).
        self.stamps: list[int] = [-1] * len(self.shapes)
        self.refreshes = 0

    def __len__(self) -> int:
        return len(self.data)

    def set(self, index: int, residual: Tensor, iteration: int) -> None:
        """Store ``residual`` [H, W, 3] (values in [0, 1]) for view ``index``."""
        r = residual.detach().clamp(0.0, 1.0)
        self.data[index] = torch.round(r * _LEVELS).to(torch.uint8)
        self.stamps[index] = int(iteration)

    def get(self, index: int, dtype=torch.float32) -> Tensor:
        """The residual of view ``index`` as float ``[H, W, 3]`` in [0, 1] (zeros if never set)."""
        return self.data[index].to(dtype) / _LEVELS

    def is_stale(self, index: int, last_refresh_point: int) -> bool:
        """Whether view ``index`` was last written before ``last_refresh_point``."""
        return self.stamps[index] < last_refresh_point

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in self.data)

    def state_dict(self) -> dict:
        return {"data": [t.clone() for t in self.data], "stamps": list(self.stamps), "refreshes": self.refreshes}

    def load_state_dict(self, state: dict) -> None:
        self.data = [t.to(self.device) for t in state["data"]]
        self.stamps = list(state["stamps"])
        self.refreshes = int(state["refreshes"])
