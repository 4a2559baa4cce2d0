"""What rain and snow share: particle slices, motion-blur kernels, the fall direction in each image.

Falling particles are transient: each view draws its own from the stream
``(scene seed, "rain" | "snow", view name)`` (:mod:`weather_synth.seeds`).  They
are rendered as *slices*: a set of particles of one size class at one depth.

Depth-aware mode gives every slice a z-depth ``z`` (in scene units): projected
sizes and streak lengths scale with ``z_ref / z`` (a drop's image size is
``f D / z``, its streak ``f v T / z``) and a slice is hidden at pixels whose
surface is nearer than ``z``.  Otherwise slices have ``z = 0``: in front of
everything and never hidden.

Pixel sizes in configs are given at a reference image width
(:data:`REFERENCE_WIDTH`) and scaled with the image, so a preset looks the same
at any resolution; densities are per reference-width pixel, so the number of
particles per image does not depend on the resolution.

Cross-CPU reproducibility: the geometry that places every particle (the fall
direction, each image's fall angle, slice depths, kernel end points) is computed
with Python's scalar maths in a fixed order and rounded far below what an image can
show (:data:`ANGLE_DECIMALS`, :data:`GEOMETRY_DECIMALS`).  numpy evaluates float64
``arctan2`` / ``tan`` / ``exp`` / ``log`` with SVML on AVX-512 CPUs and with the C
library elsewhere, and the C library picks FMA or plain code by CPU, so their last
bits differ between x86-64 machines (on one AVX-512 machine, 7 % of numpy's float64
``arctan2`` results differ by one ulp from its AVX2 path); unrounded, those bits
reached the recorded fall angles and so the dataset manifests.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from nimbus.data.camera import Camera

# Pixel sizes in rain / snow configs are for an image this wide.
REFERENCE_WIDTH = 512
# Below this blur sigma (pixels) a Gaussian blur is skipped.
MIN_SIGMA = 0.3
# Layer values below this are numerical noise of the convolution and set to 0 (1/40 of an 8-bit step).
FLOOR = 1e-4
# Decimals kept of angles (degrees) and of other particle geometry (unit vectors, depths, kernel
# end points): far below anything visible, far above the last bits that vary between CPUs.
ANGLE_DECIMALS = 9
GEOMETRY_DECIMALS = 12


def settle(x: float, decimals: int = GEOMETRY_DECIMALS) -> float:
    """``x`` rounded to ``decimals`` decimals (Python's correctly rounded ``round``): the same value on any CPU
    whose maths library gets ``x`` right to within a few ulps (module docstring)."""
    return round(float(x), decimals)


def _unit(v: np.ndarray) -> np.ndarray:
    """``v`` / its length, with CPython's ``math.hypot`` (no BLAS: its dot product may use FMA on some CPUs)."""
    return v / math.hypot(*(float(x) for x in v))


@dataclass
class ParticleSlice:
    """One rendered particle slice of a view.

    Attributes
    ----------
    kind : str
        ``"rain"`` (``layer`` is additive radiance) or ``"snow"`` (``layer`` is alpha).
    layer : ndarray, (H, W), float32, >= 0 (snow alpha <= 1)
    z : float
        z-depth of the slice in scene units; 0 = in front of everything (not depth-aware).
    """

    kind: str
    layer: np.ndarray
    z: float


def pixel_scale(width: int) -> float:
    """Factor from reference-width pixels to this image's pixels."""
    return width / REFERENCE_WIDTH


def poisson_seeds(rng: np.random.Generator, shape: tuple[int, int], per_pixel: float,
                  values: tuple[float, float]) -> np.ndarray:
    """A float32 canvas with ``Poisson(per_pixel * area)`` seeds of value ``U[values]`` at random pixels."""
    h, w = shape
    canvas = np.zeros((h, w), np.float32)
    n = int(rng.poisson(max(per_pixel, 0.0) * h * w))
    if n:
        idx = rng.integers(0, h * w, n)
        np.maximum.at(canvas.reshape(-1), idx, rng.uniform(*values, n).astype(np.float32))
    return canvas


@functools.lru_cache(maxsize=256)
def _motion_kernel_cached(length_q: int, angle_q: int, sigma_q: int) -> np.ndarray:
    length, angle, sigma = length_q / 8.0, angle_q / 8.0, sigma_q / 16.0
    half_len = max(length, 1.0) / 2
    pad = int(np.ceil(3 * sigma)) + 1
    k = 2 * (int(np.ceil(half_len)) + pad) + 1
    c = k // 2
    kern = np.zeros((k, k), np.float32)
    rad = math.radians(angle)
    dx, dy = settle(math.cos(rad) * (half_len - 0.5)), settle(math.sin(rad) * (half_len - 0.5))
    shift = 4  # sub-pixel endpoints (1/16 px)
    p0 = (int(round((c - dx) * 16)), int(round((c - dy) * 16)))
    p1 = (int(round((c + dx) * 16)), int(round((c + dy) * 16)))
    cv2.line(kern, p0, p1, 1.0, 1, cv2.LINE_AA, shift)
    if kern.sum() <= 0:
        kern[c, c] = 1.0
    if sigma >= MIN_SIGMA:
        kern = cv2.GaussianBlur(kern, (0, 0), sigma)
    kern /= kern.sum()
    kern.setflags(write=False)
    return kern


def motion_kernel(length: float, angle_deg: float, sigma: float = 0.0) -> np.ndarray:
    """A normalised (sum 1) streak kernel: an anti-aliased line ``length`` px long at ``angle_deg``
    (image x axis towards image y, i.e. clockwise on screen), blurred by a Gaussian of ``sigma`` px.

    Parameters are quantised (1/8 px, 1/8 degree, 1/16 px) so kernels are cached.
    """
    return _motion_kernel_cached(int(round(max(length, 1.0) * 8)), int(round(angle_deg * 8)) % 2880,
                                 int(round(max(sigma, 0.0) * 16)))


def convolve(canvas: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``canvas`` (float32) convolved with ``kernel`` (zero outside), values below :data:`FLOOR` set to 0.

    OpenCV convolves large kernels through the DFT, whose round-off leaves ~1e-8
    everywhere; clearing it keeps layers exactly zero away from particles (and
    compressible).
    """
    out = cv2.filter2D(canvas, cv2.CV_32F, kernel, borderType=cv2.BORDER_CONSTANT)
    out[out < FLOOR] = 0
    return out


def render_streaks(seeds: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Convolve a seed canvas with a streak kernel, scaled so an isolated seed of value v peaks at v."""
    return convolve(seeds, kernel) / np.float32(kernel.max())


def fall_direction(up: np.ndarray, tilt_deg: float, azimuth_deg: float) -> np.ndarray:
    """World direction particles fall along: ``-up`` tilted by ``tilt_deg`` towards a horizontal azimuth."""
    up = _unit(np.asarray(up, np.float64))
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = _unit(np.cross(up, a))
    e2 = np.cross(up, e1)
    az = math.radians(azimuth_deg)
    horizontal = math.cos(az) * e1 + math.sin(az) * e2
    d = _unit(-up + math.tan(math.radians(tilt_deg)) * horizontal)
    return np.array([settle(x) for x in d])


def image_fall_angle(camera: Camera, direction: np.ndarray, depth: float = 1.0) -> float:
    """Angle (degrees, x towards y) of a world direction as seen at the image centre.

    Projects a short segment along ``direction`` from the point ``depth`` in front
    of the camera's principal point.  When the direction is (nearly) along the
    optical axis the streaks would be dots; the vertical (90 degrees) is returned then.
    """
    R = np.asarray(camera.R, np.float64)
    d = [float(x) for x in np.asarray(direction, np.float64).reshape(3)]
    # R @ d written out: a BLAS product may contract to FMA on some CPUs and not on others.
    d_cam = [float(R[i, 0]) * d[0] + float(R[i, 1]) * d[1] + float(R[i, 2]) * d[2] for i in range(3)]
    q = [0.05 * depth * d_cam[0], 0.05 * depth * d_cam[1], depth + 0.05 * depth * d_cam[2]]
    if q[2] <= 1e-9:
        return 90.0
    du = camera.fx * (q[0] / q[2])
    dv = camera.fy * (q[1] / q[2])
    if math.hypot(du, dv) < 1e-3 * camera.fx * 0.05:
        return 90.0
    return settle(math.degrees(math.atan2(dv, du)), ANGLE_DECIMALS)


def slice_depths(rng: np.random.Generator, depth_range: tuple[float, float], count: int, scale: float) -> np.ndarray:
    """``count`` slice depths stratified in log-depth over ``depth_range * scale`` (one per stratum, jittered)."""
    lo, hi = math.log(depth_range[0] * scale), math.log(depth_range[1] * scale)
    u = (np.arange(count) + rng.uniform(0, 1, count)) / count
    return np.array([settle(math.exp(lo + float(x) * (hi - lo))) for x in u])


def hide_behind(layer: np.ndarray, z: float, surface_depth: np.ndarray | None) -> np.ndarray:
    """Zero the slice where the scene surface is nearer than the slice (depth-aware occlusion)."""
    if surface_depth is None or z <= 0:
        return layer
    return np.where(surface_depth < z, np.float32(0), layer)


def depth_slices(rng: np.random.Generator, depth_range: tuple[float, float], count: int, scale: float,
                 depth_aware: bool) -> list[tuple[float, float]]:
    """``(z, k)`` of each slice of a particle family: its depth and its size factor ``z_ref / z``.

    Depth-aware: ``count`` slices from :func:`slice_depths` (``z_ref`` the geometric mean of the
    range, in scene units).  Otherwise one slice in front of everything, ``(0, 1)``, and no draw
    from ``rng``.
    """
    if not depth_aware:
        return [(0.0, 1.0)]
    z_ref = np.sqrt(depth_range[0] * depth_range[1]) * scale
    # z_ref / z with z the array's float64 item, as the rain and snow loops always computed it
    return [(float(z), z_ref / z) for z in slice_depths(rng, depth_range, count, scale)]


@dataclass
class ParticleResult:
    """One view's rain or snow: its slices and JSON-able ``info`` (``angle_deg`` and one record per family)."""

    slices: list[ParticleSlice] = field(default_factory=list)
    info: dict = field(default_factory=dict)

    @classmethod
    def start(cls, camera: Camera, fall_dir: np.ndarray, families: str) -> "ParticleResult":
        """An empty result for ``camera``, ``info`` holding the fall angle and an empty list ``families``."""
        return cls(info={"angle_deg": image_fall_angle(camera, fall_dir), families: []})

    def add(self, kind: str, layer: np.ndarray, z: float, surface_depth: np.ndarray | None) -> None:
        """Append a slice at depth ``z``, hidden behind nearer surfaces (never at ``z`` 0 or without ``surface_depth``)."""
        self.slices.append(ParticleSlice(kind, hide_behind(layer, z, surface_depth).astype(np.float32), z))


def coverage(slices: list[ParticleSlice], shape: tuple[int, int], threshold: float = 0.01) -> float:
    """Fraction of pixels where any slice exceeds ``threshold``."""
    if not slices:
        return 0.0
    m = np.zeros(shape, bool)
    for s in slices:
        m |= s.layer > threshold
    return float(m.mean())
