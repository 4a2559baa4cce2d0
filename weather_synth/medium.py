"""World-space participating media (haze, fog): extinction fields and optical depth along rays.

A medium is ONE field ``beta(p)`` (extinction per scene unit) over world points,
so every view of a scene looks through the same fog: a world point has one
extinction value whichever camera samples it, and the transmission of a ray
segment is ``exp(-tau)`` with the optical depth ``tau = integral of beta``
along it (additive along a ray).  Image-space noise, as 2D augmentation
libraries use, cannot have these properties.

Two media:

:class:`HomogeneousMedium`
    ``beta(p) = beta``; ``tau = beta * L``.
:class:`HeightFogMedium`
    Exponential height fog modulated by smooth 3D noise::

        beta(p) = a * exp(-b * h(p)) * (1 + c * (2 N(p) - 1))

    with ``h(p) = (p - origin) . up`` the height above the reference point,
    ``N`` fractal value noise in [0, 1] (seeded by the scene seed) and
    ``0 <= c <= 1`` so beta never goes negative.  Its optical depth is the
    closed form of the exponential part plus a Gauss-Legendre quadrature of the
    noise part (see :meth:`HeightFogMedium.optical_depth`).

Infinite ray lengths (sky, backdrop) are allowed: ``tau`` is ``inf`` unless the
medium thins out along the ray (height fog looking upward), and 0 for an empty
medium (never ``0 * inf = NaN``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from nimbus.data.camera import Camera
from nimbus.errors import NimbusError
from weather_synth.particles import settle

# Gauss-Legendre nodes/weights on [-1, 1]; 3 points integrate quintics exactly per segment.
_GL_X, _GL_W = np.polynomial.legendre.leggauss(3)


# --- smooth 3D noise -----------------------------------------------------------------------
# Value noise reads a periodic lattice of this many cells per axis (the largest features repeat
# every LATTICE noise scales, far beyond any scene).
LATTICE = 64


@functools.lru_cache(maxsize=8)
def _lattice(seed: int) -> np.ndarray:
    """The flat (LATTICE**3,) table of uniform [0, 1) lattice values for a seed (PCG64, stable everywhere)."""
    table = np.random.Generator(np.random.PCG64(seed)).random(LATTICE ** 3, dtype=np.float32)
    table.setflags(write=False)
    return table


def value_noise(p: np.ndarray, seed: int) -> np.ndarray:
    """Smooth 3D value noise in [0, 1] at points ``p`` (..., 3) in lattice units (C2: quintic fade), float32."""
    p = np.asarray(p, dtype=np.float64)
    i0 = np.floor(p)
    f = (p - i0).astype(np.float32)
    w = f * f * f * (f * (f * 6 - 15) + 10)
    i0 = i0.astype(np.int64) & (LATTICE - 1)
    i1 = (i0 + 1) & (LATTICE - 1)
    table = _lattice(int(seed))
    x0, x1 = i0[..., 0] * LATTICE * LATTICE, i1[..., 0] * LATTICE * LATTICE
    y0, y1 = i0[..., 1] * LATTICE, i1[..., 1] * LATTICE
    z0, z1 = i0[..., 2], i1[..., 2]
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]

    def lerp(a, b, t):
        return a + (b - a) * t

    def edge(xo, yo):
        return lerp(table[xo + yo + z0], table[xo + yo + z1], wz)

    return lerp(lerp(edge(x0, y0), edge(x0, y1), wy), lerp(edge(x1, y0), edge(x1, y1), wy), wx)


def fractal_noise(p: np.ndarray, seed: int, octaves: int = 3, lacunarity: float = 2.0, gain: float = 0.5) -> np.ndarray:
    """Fractal sum of :func:`value_noise` octaves, normalised to [0, 1], float32;
    ``p`` (..., 3) in units of the largest feature."""
    total = np.zeros(np.shape(p)[:-1], np.float32)
    amp, freq, norm = 1.0, 1.0, 0.0
    for k in range(octaves):
        total += np.float32(amp) * value_noise(np.asarray(p) * freq + 17.31 * k, seed + 7919 * k)
        norm += amp
        amp *= gain
        freq *= lacunarity
    return total / np.float32(norm)


# --- media ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class HomogeneousMedium:
    """Constant extinction ``beta`` (1 / scene unit), ``beta >= 0``."""

    beta: float

    def __post_init__(self) -> None:
        check_beta(self.beta)

    def extinction(self, points: np.ndarray) -> np.ndarray:
        """beta at world points (N, 3) -> (N,)."""
        return np.full(np.shape(points)[:-1], float(self.beta))

    def optical_depth(self, origins: np.ndarray, dirs: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        """``beta * L`` for rays of length ``lengths`` (N,) (``inf`` allowed; 0 when beta = 0)."""
        lengths = np.asarray(lengths, dtype=np.float64)
        if self.beta == 0:
            return np.zeros_like(lengths)
        with np.errstate(invalid="ignore"):
            # A zero-length ray has zero optical depth even in an opaque (beta = inf) medium.
            return np.where(lengths > 0, self.beta * lengths, 0.0)


@dataclass(frozen=True)
class HeightFogMedium:
    """Exponential height fog times smooth 3D noise (see the module docstring).

    Attributes
    ----------
    density : float
        ``a``: extinction at the reference height, 1 / scene unit, >= 0.
    falloff : float
        ``b``: 1 / scale height (1 / scene unit), >= 0; 0 makes the fog uniform in height.
    up : tuple of 3 floats
        World up direction (normalised here).
    origin : tuple of 3 floats
        A world point at height 0 (e.g. the mean camera centre).
    noise_amplitude : float
        ``c`` in [0, 1]: relative strength of the noise modulation (0 = pure height fog).
    noise_scale : float
        Size of the largest noise feature, scene units, > 0.
    noise_octaves : int
        Fractal octaves of the noise.
    noise_far : float
        The noise part is integrated up to this distance along a ray (scene units);
        beyond it only the closed-form part counts (the noise has zero mean, so the
        error is small).  Finite ray lengths below it are integrated exactly up to
        quadrature error.
    step : float or None
        Quadrature segment length (3 Gauss-Legendre nodes each); default ``noise_scale / 4``.
    max_segments : int
        Upper bound on quadrature segments per ray (bounds memory and time).
    seed : int
        Noise seed (derive it from the scene seed so every view sees the same fog).
    """

    density: float
    falloff: float
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    noise_amplitude: float = 0.6
    noise_scale: float = 1.0
    noise_octaves: int = 3
    noise_far: float = 10.0
    step: float | None = None
    max_segments: int = 256
    seed: int = 0

    def __post_init__(self) -> None:
        check_beta(self.density, "fog density")
        if not (np.isfinite(self.falloff) and self.falloff >= 0):
            raise NimbusError(f"fog falloff must be finite and >= 0 (1 / scale height), got {self.falloff}")
        if not 0.0 <= self.noise_amplitude <= 1.0:
            raise NimbusError(f"fog noise amplitude must be in [0, 1], got {self.noise_amplitude}")
        if not (self.noise_scale > 0 and np.isfinite(self.noise_scale)):
            raise NimbusError(f"fog noise scale must be positive, got {self.noise_scale}")
        up = np.asarray(self.up, dtype=np.float64)
        if not np.isfinite(up).all() or np.linalg.norm(up) < 1e-12:
            raise NimbusError(f"fog up vector must be a non-zero direction, got {self.up}")
        object.__setattr__(self, "up", tuple(float(x) for x in up / np.linalg.norm(up)))
        object.__setattr__(self, "origin", tuple(float(x) for x in self.origin))

    # --- field -------------------------------------------------------------------------
    def height(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=np.float64) - np.asarray(self.origin)) @ np.asarray(self.up)

    def noise(self, points: np.ndarray) -> np.ndarray:
        """N(p) in [0, 1] at world points (..., 3)."""
        return fractal_noise(np.asarray(points, dtype=np.float64) / self.noise_scale, self.seed, self.noise_octaves)

    def extinction(self, points: np.ndarray) -> np.ndarray:
        """beta(p) at world points (..., 3) -> (...), 1 / scene unit."""
        with np.errstate(over="ignore"):
            base = self.density * np.exp(-self.falloff * self.height(points))
        return base * (1.0 + self.noise_amplitude * (2.0 * self.noise(points) - 1.0))

    # --- optical depth ---------------------------------------------------------------------
    @property
    def noise_free(self) -> bool:
        """The noise part adds nothing: no fog, no modulation, or an opaque fog (``density = inf``),
        whose exponential part is already ``inf`` and where ``inf * (2 N - 1)`` would mix
        ``+inf`` and ``-inf`` into NaN."""
        return self.density == 0 or self.noise_amplitude == 0 or bool(np.isinf(self.density))

    def exponential_depth(self, origins: np.ndarray, dirs: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        """Closed-form optical depth of the height-exponential part ``a exp(-b h)``.

        ``tau = a exp(-b h0) * L * (1 - exp(-x)) / x`` with ``x = b (d . up) L``
        (-> ``a exp(-b h0) L`` as x -> 0); for ``L = inf`` it is
        ``a exp(-b h0) / (b (d . up))`` looking upward and ``inf`` otherwise.
        """
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        L = np.broadcast_to(np.asarray(lengths, dtype=np.float64),
                            np.broadcast_shapes(o.shape[:-1], d.shape[:-1], np.shape(lengths)))
        if self.density == 0:
            return np.zeros(L.shape)
        h0 = self.height(o)
        dy = d @ np.asarray(self.up)
        b = self.falloff
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            scale = self.density * np.exp(-b * h0)
            finite = np.isfinite(L)
            Lf = np.where(finite, L, 0.0)
            x = b * dy * Lf
            small = np.abs(x) < 1e-8
            ratio = np.where(small, 1.0 - 0.5 * x, -np.expm1(-x) / np.where(small, 1.0, x))
            tau_finite = scale * Lf * ratio
            up_inf = (b > 0) & (dy > 0)
            tau_inf = np.where(up_inf, scale / np.where(up_inf, b * dy, 1.0), np.inf)
            tau = np.where(finite, tau_finite, tau_inf)
        return np.where(np.isnan(tau), np.inf, tau)

    def _noise_integrand(self, o: np.ndarray, d: np.ndarray, s: np.ndarray) -> np.ndarray:
        """``a c exp(-b h(p)) (2 N(p) - 1)`` at ``p = o + s d``; o, d (N, 3), s (N, K) -> (N, K)."""
        p = o[:, None, :] + s[..., None] * d[:, None, :]
        with np.errstate(over="ignore"):
            base = self.density * self.noise_amplitude * np.exp(-self.falloff * self.height(p))
        return base * (2.0 * self.noise(p) - 1.0)

    def _segments(self, longest: float) -> int:
        step = self.step if self.step is not None else self.noise_scale / 4.0
        return int(np.clip(np.ceil(longest / step), 1, self.max_segments))

    def noise_depth(self, origins: np.ndarray, dirs: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        """Optical depth of the noise part up to ``min(L, noise_far)`` by composite Gauss-Legendre quadrature."""
        o = np.atleast_2d(np.asarray(origins, dtype=np.float64))
        d = np.atleast_2d(np.asarray(dirs, dtype=np.float64))
        shape = np.broadcast_shapes(o.shape[:-1], d.shape[:-1], np.shape(lengths))
        o = np.broadcast_to(o, shape + (3,)).reshape(-1, 3)
        d = np.broadcast_to(d, shape + (3,)).reshape(-1, 3)
        L = np.minimum(np.broadcast_to(np.asarray(lengths, dtype=np.float64), shape).reshape(-1), self.noise_far)
        if self.noise_free or L.size == 0:
            return np.zeros(shape)
        L = np.maximum(L, 0.0)
        n = self._segments(float(L.max()))
        k = np.arange(n)[:, None]
        frac = ((k + (_GL_X[None, :] + 1) / 2) / n).reshape(-1)          # node positions in [0, 1]
        wts = np.tile(_GL_W / 2, n) / n                                 # weights summing to 1
        out = np.empty(len(L))
        chunk = max(1, 2_000_000 // len(frac))                           # bound the (rays x nodes x 3) working set
        for i in range(0, len(L), chunk):
            sl = slice(i, i + chunk)
            f = self._noise_integrand(o[sl], d[sl], L[sl, None] * frac[None, :])
            out[sl] = L[sl] * (f @ wts)
        return out.reshape(shape)

    def optical_depth(self, origins: np.ndarray, dirs: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        """Optical depth of rays ``o + s d``, ``0 <= s <= L``; origins/dirs (..., 3) (unit dirs), lengths (...).

        Closed form for the exponential part plus quadrature of the noise part,
        clipped at 0 (the exact integrand is never negative for ``c <= 1``).
        """
        tau = self.exponential_depth(origins, dirs, lengths) + self.noise_depth(origins, dirs, lengths)
        return np.maximum(tau, 0.0)

    def cumulative_noise_depth(self, origins: np.ndarray, dirs: np.ndarray, far: float, samples: int) -> np.ndarray:
        """Noise-part optical depth at distances ``far * j / samples``, j = 0..samples; (N, samples + 1)."""
        o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        o = np.broadcast_to(o, d.shape) if len(o) == 1 else o
        delta = far / samples
        sub = max(1, self._segments(delta))                              # quadrature segments per table interval
        k = np.arange(samples * sub)[:, None]
        s = ((k + (_GL_X[None, :] + 1) / 2) * (delta / sub)).reshape(-1)
        wts = np.tile(_GL_W / 2 * (delta / sub), samples * sub)
        out = np.zeros((len(d), samples + 1))
        if self.noise_free:
            return out
        chunk = max(1, 2_000_000 // len(s))
        for i in range(0, len(d), chunk):
            sl = slice(i, i + chunk)
            f = self._noise_integrand(o[sl], d[sl], np.broadcast_to(s, (len(d[sl]), len(s))))
            per_interval = (f * wts).reshape(len(f), samples, -1).sum(-1)
            out[sl, 1:] = np.cumsum(per_interval, axis=1)
        return out


Medium = HomogeneousMedium | HeightFogMedium


def check_beta(beta: float, what: str = "extinction coefficient beta") -> float:
    """Refuse a negative or NaN extinction (``inf`` is allowed: an opaque medium)."""
    if beta is None or np.isnan(beta) or beta < 0:
        raise NimbusError(f"{what} must be >= 0 (1 / scene unit), got {beta}; use 0 for no haze")
    return float(beta)


# --- per view ---------------------------------------------------------------------------------
class RayIntegrator:
    """Optical depth from one camera along each pixel's ray, to any per-pixel distance.

    For height fog the noise part's cumulative optical depth is tabulated once
    per camera, on rays through every ``stride``-th pixel at ``table_samples + 1``
    distances up to ``noise_far``, and interpolated bilinearly over the image
    and linearly along the ray (it is smooth in both); the exponential part is
    exact at every pixel.  So transmissions to the surface and to any number of
    particle depths cost one table.

    Parameters
    ----------
    medium : HomogeneousMedium or HeightFogMedium
    camera : Camera
    stride : int
        Table spacing in pixels (1 = every pixel).
    table_samples : int
        Tabulated distances per ray.
    """

    def __init__(self, medium: Medium, camera: Camera, stride: int = 4, table_samples: int = 48) -> None:
        self.medium = medium
        self.camera = camera
        self.stride = max(1, int(stride))
        self.table_samples = int(table_samples)
        self._dirs = None
        self._table = None

    def _noise_table(self) -> np.ndarray:
        if self._table is None:
            cam, s = self.camera, self.stride
            W, H = cam.width, cam.height
            # Coarse rays through the centres of s x s pixel blocks (pixel centres sit at u + 0.5).
            uc = np.minimum((np.arange(-(-W // s)) + 0.5) * s, W)
            vc = np.minimum((np.arange(-(-H // s)) + 0.5) * s, H)
            uu, vv = np.meshgrid((uc - cam.cx) / cam.fx, (vc - cam.cy) / cam.fy)
            d_cam = np.stack([uu, vv, np.ones_like(uu)], -1)
            d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
            table = self.medium.cumulative_noise_depth(cam.center, (d_cam @ cam.R).reshape(-1, 3),
                                                       self.medium.noise_far, self.table_samples)
            table = table.reshape(len(vc), len(uc), -1).astype(np.float32)
            # Full-resolution pixel (u + 0.5) sits at coarse index (u + 0.5) / s - 0.5.
            mx, my = np.meshgrid(((np.arange(W) + 0.5) / s - 0.5).astype(np.float32),
                                 ((np.arange(H) + 0.5) / s - 0.5).astype(np.float32))
            self._table = _remap_channels(table, mx, my)
        return self._table

    def __call__(self, distance: np.ndarray) -> np.ndarray:
        """Optical depth (H, W), float64, >= 0 (``inf`` allowed) to ray distances ``distance`` (H, W)."""
        distance = np.asarray(distance, dtype=np.float64)
        m = self.medium
        if isinstance(m, HomogeneousMedium):
            return m.optical_depth(None, None, distance)
        if self._dirs is None:
            self._dirs = self.camera.world_rays(np.float64)[0]
        tau = m.exponential_depth(self.camera.center, self._dirs, distance)
        if m.noise_free:
            return tau
        full = self._noise_table()
        n = self.table_samples
        pos = np.clip(np.where(np.isfinite(distance), distance, m.noise_far), 0, m.noise_far) / m.noise_far * n
        j0 = np.minimum(np.floor(pos).astype(np.int64), n - 1)
        frac = pos - j0
        t0 = np.take_along_axis(full, j0[..., None], -1)[..., 0]
        t1 = np.take_along_axis(full, (j0 + 1)[..., None], -1)[..., 0]
        return np.maximum(tau + (1 - frac) * t0 + frac * t1, 0.0)


def _remap_channels(table: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Bilinear resampling of an (h, w, C) table at float maps (OpenCV handles at most 512 channels at once)."""
    parts = [cv2.remap(np.ascontiguousarray(table[..., i:i + 256]), mx, my, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE) for i in range(0, table.shape[-1], 256)]
    parts = [p[..., None] if p.ndim == 2 else p for p in parts]
    return np.concatenate(parts, axis=-1).astype(np.float64)


def estimate_up(cameras: list[Camera]) -> np.ndarray:
    """World up direction as the mean of the cameras' up axes (OpenCV -y), normalised.

    People hold cameras roughly upright, so this recovers the vertical of a
    COLMAP model (whose axes are arbitrary) to within the cameras' mean roll/pitch.
    """
    if not cameras:
        raise NimbusError("cannot estimate the up direction of a scene without views")
    up = -np.mean([np.asarray(c.R, np.float64)[1] for c in cameras], axis=0)
    # math.hypot, not np.linalg.norm (a BLAS dot product that rounds differently on different CPUs), and
    # rounded like the particle geometry: the recorded up vector is the same on every CPU.
    n = math.hypot(*(float(x) for x in up))
    return np.array([settle(x / n) for x in up]) if n > 1e-9 else np.array([0.0, 0.0, 1.0])
