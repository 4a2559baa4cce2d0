"""Rain: procedural streak layers, per view, additive (OneRestore / RainStreakGen style).

Each view gets several streak *layers* like RainStreakGen's dense / middle /
sparse: sparse random seeds (a Poisson number at random pixels, values
``U[0.6, 1]``), drawn out by a motion-blur kernel (a line of the layer's
length along the fall direction, thickened by a Gaussian of the layer's width),
scaled so an isolated streak peaks at its seed value, clipped to 1 ("levels")
and multiplied by the layer's weight ``U[weight]``.  Far layers are dense,
short and thin; near layers sparse, long, wide and faint.  The rain layer is
added to the image (OneRestore: ``I = J + R``), so drops are bright whatever
the background, as Garg & Nayar observed.

The streak angle of a view is the scene's fall direction (straight down, tilted
by a per-scene wind, :func:`~weather_synth.particles.fall_direction`) projected at the image centre, plus a small per-layer
jitter: views looking the same way see rain falling the same way.

Depth-aware (see :mod:`weather_synth.particles`): each layer is split into
slices at stratified depths within its depth range (in depth-scale units);
length and width scale with ``z_ref / z`` (``z_ref`` the geometric mean of the
range) and a slice is hidden behind nearer surfaces.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from nimbus.config_validation import Limit, at_least, between
from nimbus.data.camera import Camera
from nimbus.errors import NimbusError
from weather_synth.particles import (
    ParticleResult,
    depth_slices,
    motion_kernel,
    pixel_scale,
    poisson_seeds,
    render_streaks,
)

RAIN_PRESETS = ("light", "medium", "heavy")
#: Depth slices per streak layer at most: each is a full-image layer (memory grows with it), and 64 depths are finer
#: than the eye tells apart.
MAX_SLICES = 64
# Bounds beyond which rain stops being rain (issue 35: absurd amounts gave silent garbage, or allocated without end).
#: amount multiplies a streak's peak brightness: at 10 the faintest default layer (0.10-0.20) already peaks at white,
#: so more only clips every streak to white.
MAX_RAIN_AMOUNT = 10.0
#: density_scale multiplies streaks per pixel: at 1000 the dense layer seeds 3 streaks on every pixel, each 14-26
#: pixels long, so the image is covered many times over (the seeds and their memory grow with it, without end).
MAX_RAIN_DENSITY_SCALE = 1000.0
#: length_scale multiplies streak lengths: at 5 the longest default streak (90 reference pixels) is 450 of the
#: reference width's 512; a streak longer than the image is no streak (and its kernel grows with the square).
MAX_RAIN_LENGTH_SCALE = 5.0
# Cross-section sigma (pixels) of an anti-aliased one-pixel line: thinner streaks are dimmed instead.
LINE_SIGMA = 0.4


@dataclass(frozen=True)
class StreakLayer:
    """One family of streaks.

    Attributes
    ----------
    name : str
    density : float
        Streaks per reference-width pixel (:data:`~weather_synth.particles.REFERENCE_WIDTH`).
    length : (float, float)
        Streak length range, reference-width pixels (drawn per view).
    width : float
        Gaussian sigma of the streak's cross-section, reference-width pixels.
    weight : (float, float)
        Peak brightness range of the layer (drawn per view).
    depth : (float, float)
        Depth-aware: z-depth range in depth-scale units.
    """

    name: str
    density: float
    length: tuple[float, float]
    width: float
    weight: tuple[float, float]
    depth: tuple[float, float]


# RainStreakGen: dense (weight 0.25-0.45, thin), middle (0.20-0.35, blurrier), sparse (0.10-0.20, large).
DEFAULT_LAYERS = (
    StreakLayer("dense", 0.0030, (14.0, 26.0), 0.5, (0.25, 0.45), (1.0, 2.5)),
    StreakLayer("middle", 0.0010, (26.0, 48.0), 1.0, (0.20, 0.35), (0.35, 1.0)),
    StreakLayer("sparse", 0.00025, (48.0, 90.0), 1.8, (0.10, 0.20), (0.1, 0.35)),
)


@dataclass(frozen=True)
class RainConfig:
    """Rain parameters.  Presets: :func:`rain_preset` (``light`` / ``medium`` / ``heavy``).

    Attributes
    ----------
    amount : float
        Multiplies every layer's weight (0 = no rain, the image is unchanged;
        huge values saturate to white).
    density_scale : float
        Multiplies every layer's density.
    length_scale : float
        Multiplies every layer's streak length.
    layers : tuple of StreakLayer
    angle_jitter : float
        Per-layer, per-view jitter of the streak angle, degrees (+-).
    slices : int
        Depth-aware: slices per layer.
    """

    amount: float = 1.0
    density_scale: float = 1.0
    length_scale: float = 1.0
    layers: tuple[StreakLayer, ...] = DEFAULT_LAYERS
    angle_jitter: float = 3.0
    slices: int = 2

    #: The accepted values of each field (see :mod:`nimbus.config_validation`).
    LIMITS: ClassVar[dict[str, Limit]] = {
        "amount": between(0, MAX_RAIN_AMOUNT, note="10: every streak peaks at white"),
        "density_scale": between(0, MAX_RAIN_DENSITY_SCALE, note="1000: 3 streaks on every pixel"),
        "length_scale": between(0, MAX_RAIN_LENGTH_SCALE, note="5: the longest streak nearly spans the image"),
        "angle_jitter": between(0, 90, note="degrees"),
        "slices": between(1, MAX_SLICES, note="full-image layers per streak layer"),
    }

    def __post_init__(self) -> None:
        for name in ("amount", "density_scale", "length_scale"):
            v = getattr(self, name)
            if not (v >= 0 and np.isfinite(v)):
                raise NimbusError(f"rain {name} must be a finite number >= 0, got {v}")
        if self.slices < 1:
            raise NimbusError(f"rain slices must be >= 1, got {self.slices}")
        for layer in self.layers:
            if layer.density < 0 or layer.width < 0 or min(layer.length) <= 0 or min(layer.weight) < 0 \
                    or min(layer.depth) <= 0 or layer.depth[0] > layer.depth[1]:
                raise NimbusError(f"rain layer {layer.name}: densities, widths and weights must be >= 0, "
                                  f"lengths and depths positive with lo <= hi")

    @property
    def active(self) -> bool:
        return self.amount > 0 and self.density_scale > 0 and any(l.density > 0 for l in self.layers)


_PRESET_SCALES = {  # (amount, density_scale, length_scale)
    "light": (0.8, 0.4, 0.8),
    "medium": (1.0, 1.0, 1.0),
    "heavy": (1.2, 2.5, 1.2),
}


def rain_preset(name: str, **overrides) -> RainConfig:
    """The named intensity preset (``light``, ``medium``, ``heavy``) with optional field overrides."""
    key = str(name).lower()
    if key not in _PRESET_SCALES:
        raise NimbusError(f"unknown rain intensity {name!r}; use one of {RAIN_PRESETS} or a number (amount)")
    amount, dens, length = _PRESET_SCALES[key]
    return replace(RainConfig(amount=amount, density_scale=dens, length_scale=length), **overrides)


def render_rain(camera: Camera, rng: np.random.Generator, config: RainConfig, fall_dir: np.ndarray,
                surface_depth: np.ndarray | None = None, depth_scale: float = 1.0,
                depth_aware: bool = False) -> ParticleResult:
    """Render one view's rain slices.

    Parameters
    ----------
    camera : Camera
    rng : Generator
        The view's rain stream (``rng_for(seed, "rain", view name)``).
    config : RainConfig
    fall_dir : (3,) array
        World fall direction (:func:`~weather_synth.particles.fall_direction`).
    surface_depth : (H, W) float32 or None
        Scene z-depth for depth-aware occlusion.
    depth_scale : float
        Scene depth scale (slice depths are in these units).
    depth_aware : bool

    Returns
    -------
    ParticleResult
        ``slices`` (additive layers, float32 (H, W)) and JSON-able ``info``.
    """
    H, W = camera.height, camera.width
    px = pixel_scale(W)
    result = ParticleResult.start(camera, fall_dir, "layers")
    if not config.active:
        return result
    n_slices = config.slices if depth_aware else 1
    for layer in config.layers:
        weight = float(rng.uniform(*layer.weight)) * config.amount
        length = float(rng.uniform(*layer.length)) * config.length_scale
        angle = result.info["angle_deg"] + float(rng.uniform(-config.angle_jitter, config.angle_jitter))
        rec = {"name": layer.name, "weight": weight, "length_px": length * px, "angle_deg": angle, "slices": []}
        for z, k in depth_slices(rng, layer.depth, n_slices, depth_scale, depth_aware):
            L_true = length * px * k
            sigma = layer.width * px * k
            L = max(1.0, L_true)
            # A streak thinner or shorter than a pixel is drawn one pixel wide / long; dim it so
            # that it carries the light of the true streak (rain turns into a faint veil at low resolution).
            dim = min(1.0, sigma / LINE_SIGMA) * min(1.0, L_true)
            kernel = motion_kernel(L, angle, sigma)
            pad = kernel.shape[0] // 2
            per_pixel = layer.density * config.density_scale / (px * px) / n_slices
            seeds = poisson_seeds(rng, (H + 2 * pad, W + 2 * pad), per_pixel, (0.6, 1.0))
            streaks = render_streaks(seeds, kernel)[pad:pad + H, pad:pad + W]
            streaks = np.minimum(streaks, np.float32(1)) * np.float32(weight * dim)
            result.add("rain", streaks, z, surface_depth)
            rec["slices"].append({"z": z, "length_px": float(L_true), "sigma_px": float(sigma),
                                  "brightness": float(weight * dim)})
        result.info["layers"].append(rec)
    return result
