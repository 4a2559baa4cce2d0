"""Snow: procedural flake masks, per view, alpha-over toward white (OneRestore / Snow100K style).

Flakes come in size classes (small and many, large and few, as in Snow100K's
masks).  Each flake is an anti-aliased disc of radius ``U[radius]`` and opacity
``U[opacity]`` at a random sub-pixel position; a class is then blurred
(defocus, ``blur`` px) and smeared by a short motion streak along the fall
direction (flakes fall at 0.5-2 m/s, so streaks are short; ``flutter`` adds
a per-class angle jitter, flakes drift).  The result is an alpha mask ``M`` in
[0, 1] composited as OneRestore does: ``I = J (1 - M) + C M`` with ``C = 1``
(white, :attr:`SnowConfig.color`).

Depth-aware (see :mod:`weather_synth.particles`): each class is split into
slices at stratified depths; radius, blur and streak length scale with
``z_ref / z`` and a slice is hidden behind nearer surfaces.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import ClassVar

import cv2
import numpy as np

from nimbus.config_validation import Limit, at_least, between, fraction
from nimbus.data.camera import Camera
from nimbus.errors import NimbusError
from weather_synth.particles import (
    MIN_SIGMA,
    ParticleResult,
    convolve,
    depth_slices,
    motion_kernel,
    pixel_scale,
)

SNOW_PRESETS = ("light", "medium", "heavy")
#: Depth slices per class at most: each is a full-image layer (memory grows with it), and 64 depths are finer
#: than the eye tells apart.
MAX_SLICES = 64
# Bounds beyond which snow stops being snowfall (issue 35: absurd amounts gave silent garbage).
#: amount multiplies flakes per pixel: at 250 the small class alone drops one flake on every reference pixel, and
#: the image is a white veil; more changes nothing.
MAX_SNOW_AMOUNT = 250.0
#: size_scale multiplies flake radii, blur and streaks: at 5 the largest flakes are 25 reference pixels across
#: their radius and streak 70; beyond, a flake is a blot over a tenth of the image (and its canvas padding grows).
MAX_SNOW_SIZE_SCALE = 5.0
# Flake centres and radii are drawn with 1/16-pixel precision (cv2 drawing shift).
_SHIFT = 4
# Smallest flake radius drawn (pixels); smaller flakes are drawn this size with proportionally less alpha.
MIN_RADIUS = 0.6


@dataclass(frozen=True)
class FlakeClass:
    """One size class of snowflakes.

    Attributes
    ----------
    name : str
    density : float
        Flakes per reference-width pixel.
    radius : (float, float)
        Flake radius range, reference-width pixels.
    opacity : (float, float)
        Flake alpha range.
    blur : float
        Defocus Gaussian sigma, reference-width pixels.
    streak : (float, float)
        Motion streak length range (per view), reference-width pixels.
    flutter : float
        Per-view jitter of the streak angle, degrees (+-).
    depth : (float, float)
        Depth-aware: z-depth range in depth-scale units.
    """

    name: str
    density: float
    radius: tuple[float, float]
    opacity: tuple[float, float]
    blur: float
    streak: tuple[float, float]
    flutter: float
    depth: tuple[float, float]


DEFAULT_CLASSES = (
    FlakeClass("small", 0.0040, (0.5, 1.3), (0.45, 0.9), 0.6, (1.0, 5.0), 15.0, (0.8, 2.5)),
    FlakeClass("medium", 0.0006, (1.3, 2.6), (0.6, 0.95), 1.0, (2.0, 8.0), 20.0, (0.3, 0.8)),
    FlakeClass("large", 0.00008, (2.6, 5.0), (0.7, 1.0), 2.0, (4.0, 14.0), 25.0, (0.1, 0.3)),
)


@dataclass(frozen=True)
class SnowConfig:
    """Snow parameters.  Presets: :func:`snow_preset` (``light`` / ``medium`` / ``heavy``).

    Attributes
    ----------
    amount : float
        Multiplies every class's density (0 = no snow, the image is unchanged;
        huge values saturate to white).
    size_scale : float
        Multiplies flake radii, blur and streak lengths.
    classes : tuple of FlakeClass
    color : float
        Snow colour ``C`` (grey, display value; OneRestore: 1.0).
    slices : int
        Depth-aware: slices per class.
    """

    amount: float = 1.0
    size_scale: float = 1.0
    classes: tuple[FlakeClass, ...] = DEFAULT_CLASSES
    color: float = 1.0
    slices: int = 2

    #: The accepted values of each field (see :mod:`nimbus.config_validation`).
    LIMITS: ClassVar[dict[str, Limit]] = {
        "amount": between(0, MAX_SNOW_AMOUNT, note="250: a flake on every pixel"),
        "size_scale": between(0, MAX_SNOW_SIZE_SCALE, note="5: flakes 25 pixels in radius"), "color": fraction(),
        "slices": between(1, MAX_SLICES, note="full-image layers per class"),
    }

    def __post_init__(self) -> None:
        for name in ("amount", "size_scale"):
            v = getattr(self, name)
            if not (v >= 0 and np.isfinite(v)):
                raise NimbusError(f"snow {name} must be a finite number >= 0, got {v}")
        if not 0 <= self.color <= 1:
            raise NimbusError(f"snow colour must be in [0, 1], got {self.color}")
        if self.slices < 1:
            raise NimbusError(f"snow slices must be >= 1, got {self.slices}")
        for c in self.classes:
            if c.density < 0 or min(c.radius) <= 0 or not (0 <= c.opacity[0] <= c.opacity[1] <= 1) \
                    or c.blur < 0 or min(c.streak) < 0 or min(c.depth) <= 0 or c.depth[0] > c.depth[1]:
                raise NimbusError(f"snow class {c.name}: density, blur and streak must be >= 0, radius and "
                                  "depths positive, opacity within [0, 1], ranges lo <= hi")

    @property
    def active(self) -> bool:
        return self.amount > 0 and any(c.density > 0 and c.opacity[1] > 0 for c in self.classes)


_PRESET_SCALES = {"light": (0.4, 0.9), "medium": (1.0, 1.0), "heavy": (2.5, 1.15)}  # (amount, size_scale)


def snow_preset(name: str, **overrides) -> SnowConfig:
    """The named intensity preset (``light``, ``medium``, ``heavy``) with optional field overrides."""
    key = str(name).lower()
    if key not in _PRESET_SCALES:
        raise NimbusError(f"unknown snow intensity {name!r}; use one of {SNOW_PRESETS} or a number (amount)")
    amount, size = _PRESET_SCALES[key]
    return replace(SnowConfig(amount=amount, size_scale=size), **overrides)


# At most this many flakes per canvas pixel are drawn one by one; the rest of a denser snowfall
# becomes a uniform veil of the same mean alpha (drawing millions of overlapping discs adds nothing).
MAX_FLAKES_PER_PIXEL = 0.25


def _draw_flakes(rng: np.random.Generator, shape: tuple[int, int], count: int, radius: tuple[float, float],
                 opacity: tuple[float, float]) -> np.ndarray:
    h, w = shape
    canvas = np.zeros((h, w), np.float32)
    if count == 0:
        return canvas
    xs = rng.uniform(0, w, count)
    ys = rng.uniform(0, h, count)
    rs = rng.uniform(*radius, count)
    ops = rng.uniform(*opacity, count)
    # Flakes smaller than a drawable disc are drawn at MIN_RADIUS with the alpha of their true area,
    # so coverage does not depend on the resolution.
    ops = ops * np.minimum(1.0, rs / MIN_RADIUS) ** 2
    rs = np.maximum(rs, MIN_RADIUS)
    scale = 1 << _SHIFT
    # cv2 pixel (i, j) covers [i, i+1): a centre at continuous x maps to x - 0.5.
    cx = np.round((xs - 0.5) * scale).astype(np.int64)
    cy = np.round((ys - 0.5) * scale).astype(np.int64)
    rq = np.maximum(np.round(rs * scale), 1).astype(np.int64)
    for x, y, r, a in zip(cx.tolist(), cy.tolist(), rq.tolist(), ops.tolist()):
        cv2.circle(canvas, (x, y), r, a, -1, cv2.LINE_AA, _SHIFT)
    return canvas


def render_snow(camera: Camera, rng: np.random.Generator, config: SnowConfig, fall_dir: np.ndarray,
                surface_depth: np.ndarray | None = None, depth_scale: float = 1.0,
                depth_aware: bool = False) -> ParticleResult:
    """Render one view's snow slices (alpha masks, float32 (H, W) in [0, 1]) and JSON-able info.

    Parameters are as for :func:`weather_synth.rain.render_rain`, with the view's snow stream.
    """
    H, W = camera.height, camera.width
    px = pixel_scale(W)
    result = ParticleResult.start(camera, fall_dir, "classes")
    if not config.active:
        return result
    n_slices = config.slices if depth_aware else 1
    for c in config.classes:
        streak = float(rng.uniform(*c.streak)) * config.size_scale
        angle = result.info["angle_deg"] + float(rng.uniform(-c.flutter, c.flutter))
        rec = {"name": c.name, "angle_deg": angle, "streak_px": streak * px, "slices": []}
        for z, k in depth_slices(rng, c.depth, n_slices, depth_scale, depth_aware):
            s = px * k * config.size_scale
            L = max(1.0, streak * px * k)
            kernel = motion_kernel(L, angle, max(c.blur * s, 0.0))
            pad = kernel.shape[0] // 2 + int(np.ceil(c.radius[1] * s)) + 1
            shape = (H + 2 * pad, W + 2 * pad)
            expected = c.density * config.amount / (px * px) / n_slices * shape[0] * shape[1]
            cap = MAX_FLAKES_PER_PIXEL * shape[0] * shape[1]
            count = int(rng.poisson(min(expected, cap)))
            radius = (c.radius[0] * s, c.radius[1] * s)
            flakes = _draw_flakes(rng, shape, count, radius, c.opacity)
            if kernel.size > 1 or c.blur * s >= MIN_SIGMA:
                flakes = convolve(flakes, kernel)
            alpha = np.clip(flakes[pad:pad + H, pad:pad + W], 0, 1)
            if expected > cap:
                # Undrawn flakes as a veil: Poisson discs of mean area a cover 1 - exp(-n a / area).
                area = np.pi * np.mean(np.square(np.maximum(radius, MIN_RADIUS)))
                veil = (1 - math.exp(-(expected - cap) * area / (shape[0] * shape[1]))) * np.mean(c.opacity)
                alpha = 1 - (1 - alpha) * np.float32(1 - veil)
            result.add("snow", alpha, z, surface_depth)
            rec["slices"].append({"z": z, "count": count, "radius_px": [radius[0], radius[1]],
                                  "streak_px": float(L), "blur_px": float(c.blur * s)})
        result.info["classes"].append(rec)
    return result
