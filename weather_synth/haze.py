"""Haze: atmospheric scattering from depth, ``I = J t + A (1 - t)``.

``t = exp(-tau)`` is the transmission of the pixel's ray from the camera to the
surface, ``A`` the airlight (RGB, display values in [0, 1]).  Three modes
(:attr:`HazeConfig.mode`):

``"onerestore"``
    The NimbusGS / OneRestore protocol, reproducing the paper's data.  OneRestore
    reads an 8-bit Depth-Anything map (relative *inverse* depth, min-max
    normalised per image, bright = near) and uses ``d = min(1 - box22(D), 0.7)``,
    ``t = exp(-beta d)`` with ``beta ~ U[1, 2]`` and a grey ``A ~ U[0.6, 0.9]``
    drawn per image.  Our mapping from metric depth to that map: with ``r`` the
    ray distance, ``D = (1/r - min 1/r) / (max 1/r - min 1/r)`` over the view
    (``1/inf = 0``: sky is the darkest value, as Depth-Anything predicts it),
    quantised to 8 bits (``round(255 D) / 255``), then the 22 x 22 box filter
    (:func:`cv2.blur`, reflected borders) and the 0.7 cap.  A view of constant
    depth has ``D = 0`` (far).  ``t >= exp(-0.7 beta)``: this protocol never
    fully hides the scene.  ``beta`` here is per unit of normalised depth.
``"homogeneous"``
    A physical medium of constant extinction ``beta`` (1 / scene unit), given
    directly or as a visibility distance ``V`` (``beta = 3.912 / V``, the 2 %
    contrast threshold); ``t = exp(-beta r)`` with the ray distance ``r``.
``"heterogeneous"``
    One world-space height fog with 3D noise (:class:`~weather_synth.medium.HeightFogMedium`)
    integrated along every view's rays, so all views see the same fog.

In the physical modes one medium and one airlight hold for the whole scene; the
defaults scale with the scene's depth scale (median surface distance), because
COLMAP units are arbitrary.

Extremes: ``beta = 0`` leaves the image bit for bit unchanged; an infinite
distance (sky, NaN depth) gives ``t = 0`` (pure airlight) for ``beta > 0`` and
``t = 1`` for ``beta = 0``; ``beta = inf`` gives pure airlight except at zero
distance.  Nothing produces NaN.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Callable, ClassVar

import cv2
import numpy as np

from nimbus.config_validation import Limit, at_least, between, fraction, one_of, positive
from nimbus.data.camera import Camera
from nimbus.errors import NimbusError
from nimbus.utils.jsonable import jsonable
from weather_synth.depth import ray_norm, sanitize_depth
from weather_synth.medium import HeightFogMedium, HomogeneousMedium, RayIntegrator, check_beta
from weather_synth.seeds import rng_for

HAZE_MODES = ("onerestore", "homogeneous", "heterogeneous")
SAMPLING = ("view", "scene")
# Koschmieder: visibility is where contrast falls to 2 %, -ln(0.02) = 3.912.
VISIBILITY_CONTRAST = 3.912
# Smallest ray distance used when inverting depth (a surface at the camera is the nearest possible).
_MIN_DISTANCE = 1e-12


# Upper bounds of the size-like haze settings (issue 35: 2**31 ended in a failed allocation or ran without end).
#: The onerestore box filter, in pixels: OneRestore's is 22, and the filter pads the depth map by half its size.
MAX_BOX_SIZE = 4096
#: Fractal octaves of the height fog's noise: 16 reach features 1/65536 of fog_noise_scale, below a pixel.
MAX_FOG_OCTAVES = 16
#: Tabulated distances per ray of the height fog (32 by default; the table holds rays x samples values).
MAX_FOG_TABLE_SAMPLES = 4096


@dataclass(frozen=True)
class HazeConfig:
    """Haze parameters (see the module docstring for the modes).

    Attributes
    ----------
    mode : str
        ``"onerestore"``, ``"homogeneous"`` or ``"heterogeneous"``.
    beta : float or None
        Fixed extinction.  onerestore: per unit of normalised depth (replaces the
        sampled value); physical modes: 1 / scene unit (height fog: at the mean
        camera height).  None: onerestore samples ``beta_range``; physical modes
        use ``visibility`` or ``visibility_scale``.
    beta_range : (float, float)
        onerestore: ``beta ~ U[lo, hi]`` (OneRestore: [1, 2]).
    visibility : float or None
        Physical modes: visibility distance V in scene units, ``beta = 3.912 / V``.
    visibility_scale : float
        Physical modes, when neither ``beta`` nor ``visibility`` is given:
        ``V = visibility_scale * depth scale`` (5 -> ``t ~ 0.46`` at the median surface).
    airlight : (float, float, float) or None
        Fixed RGB airlight in [0, 1] (a tint); None samples a grey value from ``airlight_range``.
    airlight_range : (float, float)
        Grey ``A ~ U[lo, hi]`` (OneRestore: [0.6, 0.9]).
    sampling : str
        onerestore: draw beta and A per ``"view"`` (as OneRestore's script, per
        image) or once per ``"scene"``.  Physical modes always draw once per scene.
    depth_cap : float
        onerestore: cap on the normalised depth ``d`` (0.7).
    box_size : int
        onerestore: box filter size in pixels (22); 1 disables it.
    quantize_depth : bool
        onerestore: quantise the normalised depth map to 8 bits as the protocol's PNG maps are.
    max_distance : float or None
        Physical modes: cap ray distances at this many scene units (the physical
        analogue of OneRestore's cap; the sky then gets ``t = exp(-tau(max))``).
    fog_height_scale : float
        Heterogeneous: scale height ``1 / b`` of the fog, in depth scales.
    fog_noise_amplitude : float
        Heterogeneous: noise modulation ``c`` in [0, 1].
    fog_noise_scale : float
        Heterogeneous: largest noise feature, in depth scales.
    fog_noise_octaves : int
        Heterogeneous: fractal octaves.
    fog_far : float
        Heterogeneous: the noise part is integrated up to this many depth scales.
    fog_grid : int
        Heterogeneous: the noise part's integral is tabulated on about this many
        rays across the image width (whatever the resolution; the noise is smooth
        across neighbouring rays) and interpolated in between.
    fog_table_samples : int
        Heterogeneous: tabulated distances per ray (up to ``fog_far``).
    """

    mode: str = "onerestore"
    beta: float | None = None
    beta_range: tuple[float, float] = (1.0, 2.0)
    visibility: float | None = None
    visibility_scale: float = 5.0
    airlight: tuple[float, float, float] | None = None
    airlight_range: tuple[float, float] = (0.6, 0.9)
    sampling: str = "view"
    depth_cap: float = 0.7
    box_size: int = 22
    quantize_depth: bool = True
    max_distance: float | None = None
    fog_height_scale: float = 1.0
    fog_noise_amplitude: float = 0.8
    fog_noise_scale: float = 1.0
    fog_noise_octaves: int = 3
    fog_far: float = 4.0
    fog_grid: int = 40
    fog_table_samples: int = 32

    #: The accepted values of each field (see :mod:`nimbus.config_validation`).
    LIMITS: ClassVar[dict[str, Limit]] = {
        "mode": one_of(*HAZE_MODES), "sampling": one_of(*SAMPLING),
        "beta": at_least(0, finite=False, note="inf: opaque"), "beta_range": at_least(0, ordered=True),
        "visibility": positive(note="scene units"), "visibility_scale": positive(),
        "airlight": fraction(scalar=True, note="R, G, B"), "airlight_range": fraction(ordered=True),
        "depth_cap": at_least(0), "box_size": between(1, MAX_BOX_SIZE, note="pixels; 1: no filter"),
        "max_distance": positive(note="scene units"),
        "fog_height_scale": positive(), "fog_noise_amplitude": fraction(), "fog_noise_scale": positive(),
        "fog_noise_octaves": between(1, MAX_FOG_OCTAVES, note="each halves the feature size"),
        "fog_far": positive(), "fog_grid": at_least(1, note="rays across the width; capped by it"),
        "fog_table_samples": between(1, MAX_FOG_TABLE_SAMPLES, note="per tabulated ray"),
    }

    def __post_init__(self) -> None:
        if self.mode not in HAZE_MODES:
            raise NimbusError(f"unknown haze mode {self.mode!r}; use one of {HAZE_MODES}")
        if self.sampling not in SAMPLING:
            raise NimbusError(f"unknown haze sampling {self.sampling!r}; use one of {SAMPLING}")
        if self.beta is not None:
            check_beta(self.beta)
        lo, hi = self.beta_range
        if not (0 <= lo <= hi and np.isfinite(hi)):
            raise NimbusError(f"beta range must satisfy 0 <= lo <= hi < inf, got {self.beta_range}")
        if self.visibility is not None:
            if self.mode == "onerestore":
                raise NimbusError("a visibility distance needs a physical haze mode (--protocol physical); "
                                  "the onerestore protocol works on normalised depth, use --beta there")
            if not self.visibility > 0:
                raise NimbusError(f"visibility must be a positive distance in scene units, got {self.visibility}")
        if not self.visibility_scale > 0:
            raise NimbusError(f"visibility_scale must be positive, got {self.visibility_scale}")
        if self.airlight is not None:
            check_airlight(self.airlight)
        lo, hi = self.airlight_range
        if not (0 <= lo <= hi <= 1):
            raise NimbusError(f"airlight range must satisfy 0 <= lo <= hi <= 1, got {self.airlight_range}")
        if not 0 <= self.depth_cap:
            raise NimbusError(f"depth cap must be >= 0, got {self.depth_cap}")
        if int(self.box_size) < 1:
            raise NimbusError(f"box size must be >= 1 pixel, got {self.box_size}")
        if self.max_distance is not None and not self.max_distance > 0:
            raise NimbusError(f"max distance must be positive, got {self.max_distance}")
        for name in ("fog_height_scale", "fog_noise_scale", "fog_far"):
            if not getattr(self, name) > 0:
                raise NimbusError(f"{name} must be positive, got {getattr(self, name)}")
        if not 0 <= self.fog_noise_amplitude <= 1:
            raise NimbusError(f"fog noise amplitude must be in [0, 1], got {self.fog_noise_amplitude}")

    @property
    def physical(self) -> bool:
        return self.mode != "onerestore"


def check_airlight(airlight) -> np.ndarray:
    """Airlight as float32 (3,) in [0, 1]; a scalar is grey.  Out-of-range values raise NimbusError."""
    a = np.asarray(airlight, dtype=np.float64).reshape(-1)
    if a.size == 1:
        a = np.repeat(a, 3)
    if a.size != 3 or not np.all(np.isfinite(a)) or np.any(a < 0) or np.any(a > 1):
        raise NimbusError(f"airlight must be one grey value or R,G,B values in [0, 1], got {airlight}")
    return a.astype(np.float32)


# --- pure functions -------------------------------------------------------------------------
def transmission_from_tau(tau: np.ndarray) -> np.ndarray:
    """``exp(-tau)`` as float32 in [0, 1] (``tau = inf`` -> 0)."""
    return np.exp(-np.asarray(tau, dtype=np.float64)).astype(np.float32)


def homogeneous_transmission(distance: np.ndarray, beta: float) -> np.ndarray:
    """``exp(-beta r)`` for ray distances ``r`` (H, W); ``beta = 0`` -> 1 everywhere (even at ``r = inf``)."""
    return transmission_from_tau(HomogeneousMedium(check_beta(beta)).optical_depth(None, None, distance))


def apply_haze(image: np.ndarray, transmission: np.ndarray, airlight) -> np.ndarray:
    """``J t + A (1 - t)``, clipped to [0, 1].

    Parameters
    ----------
    image : ndarray, (H, W, 3), float32 in [0, 1]
    transmission : ndarray, (H, W), in [0, 1]
    airlight : float or (3,), in [0, 1]

    Where ``t == 1`` the result equals the input bit for bit.
    """
    J = np.asarray(image, dtype=np.float32)
    t = np.asarray(transmission, dtype=np.float32)[..., None]
    A = check_airlight(airlight)
    return np.clip(J * t + A * (np.float32(1) - t), 0, 1)


@dataclass(frozen=True)
class InverseDepthNormalisation:
    """The per-view min-max normalisation of inverse ray distance (onerestore protocol)."""

    inv_min: float
    inv_max: float

    @classmethod
    def of(cls, distance: np.ndarray) -> "InverseDepthNormalisation":
        inv = 1.0 / np.maximum(np.asarray(distance, dtype=np.float64), _MIN_DISTANCE)
        return cls(float(inv.min()), float(inv.max()))

    def __call__(self, distance: np.ndarray) -> np.ndarray:
        """Normalised depth map D in [0, 1], bright (1) = near, float32."""
        inv = 1.0 / np.maximum(np.asarray(distance, dtype=np.float64), _MIN_DISTANCE)
        span = self.inv_max - self.inv_min
        if not span > 0:
            return np.zeros(np.shape(distance), np.float32)
        return np.clip((inv - self.inv_min) / span, 0, 1).astype(np.float32)


def onerestore_depth_map(distance: np.ndarray, quantize: bool = True) -> np.ndarray:
    """The protocol's depth map for ray distances (H, W): normalised inverse depth, bright = near, float32."""
    D = InverseDepthNormalisation.of(distance)(distance)
    return np.round(D * 255) / np.float32(255) if quantize else D


def onerestore_transmission(distance: np.ndarray, beta: float, cap: float = 0.7, box_size: int = 22,
                            quantize: bool = True) -> np.ndarray:
    """OneRestore's ``t = exp(-beta * min(1 - box(D), cap))`` from ray distances (H, W); float32."""
    beta = check_beta(beta)
    D = onerestore_depth_map(sanitize_depth(distance), quantize)
    if box_size > 1:
        D = cv2.blur(D, (int(box_size), int(box_size)), borderType=cv2.BORDER_REFLECT)
    d = np.minimum(1.0 - D.astype(np.float64), cap)
    return transmission_from_tau(_scaled(beta, d))


def _scaled(beta: float, d: np.ndarray) -> np.ndarray:
    """``beta * d`` with ``0 * inf`` and ``inf * 0`` read as 0 (no medium / no distance)."""
    if beta == 0:
        return np.zeros_like(d)
    with np.errstate(invalid="ignore"):
        return np.where(d > 0, beta * d, 0.0)


# --- per scene and per view -------------------------------------------------------------------
@dataclass
class ViewHaze:
    """The haze of one view.

    Attributes
    ----------
    transmission : ndarray, (H, W), float32 in [0, 1]
        Camera-to-surface transmission.
    airlight : ndarray, (3,), float32 in [0, 1]
    beta : float
        The extinction used (units depend on the mode).
    particle_transmission : callable
        ``f(z) -> (H, W)`` transmission from the camera to the plane at z-depth
        ``z`` along each pixel's ray (for particles at depth ``z``).
    info : dict
        JSON-able per-view values for the manifest.
    """

    transmission: np.ndarray
    airlight: np.ndarray
    beta: float
    particle_transmission: Callable[[float], np.ndarray]
    info: dict


class HazeModel:
    """Scene-level haze: samples or derives the parameters and makes each view's :class:`ViewHaze`.

    Parameters
    ----------
    config : HazeConfig
    seed : int
        The scene seed (streams ``("haze",)`` and ``("haze", view name)``).
    depth_scale : float
        The scene's median surface distance (scene units), for the physical defaults.
    up, origin : (3,) arrays
        World up and the reference point of height 0 (height fog).
    """

    def __init__(self, config: HazeConfig, seed: int, depth_scale: float, up=(0, 0, 1), origin=(0, 0, 0)) -> None:
        self.config = config
        self.seed = int(seed)
        self.depth_scale = float(depth_scale)
        c = config
        scene_rng = rng_for(seed, "haze")
        self._scene_beta, self._scene_airlight = self._draw(scene_rng)
        self.medium = None
        if c.physical:
            if c.beta is not None:
                beta = c.beta
            elif c.visibility is not None:
                beta = VISIBILITY_CONTRAST / c.visibility
            else:
                beta = VISIBILITY_CONTRAST / (c.visibility_scale * self.depth_scale)
            self._scene_beta = float(beta)
            if c.mode == "homogeneous":
                self.medium = HomogeneousMedium(beta)
            else:
                s = self.depth_scale
                self.medium = HeightFogMedium(
                    density=beta, falloff=1.0 / (c.fog_height_scale * s), up=tuple(np.asarray(up, float)),
                    origin=tuple(np.asarray(origin, float)), noise_amplitude=c.fog_noise_amplitude,
                    noise_scale=c.fog_noise_scale * s, noise_octaves=c.fog_noise_octaves,
                    noise_far=c.fog_far * s, seed=int(scene_rng.integers(2**31)))

    def _draw(self, rng: np.random.Generator) -> tuple[float, np.ndarray]:
        c = self.config
        beta = c.beta if c.beta is not None else float(rng.uniform(*c.beta_range))
        if c.airlight is not None:
            airlight = check_airlight(c.airlight)
        else:
            airlight = check_airlight(float(rng.uniform(*c.airlight_range)))
        return float(beta), airlight

    def describe(self) -> dict:
        """Scene-level parameters for the manifest."""
        d = {"config": jsonable(asdict(self.config), nonfinite="text"), "depth_scale": self.depth_scale}
        if self.config.physical or self.config.sampling == "scene":
            d["beta"] = self._scene_beta
            d["airlight"] = self._scene_airlight.tolist()
        if isinstance(self.medium, HeightFogMedium):
            d["medium"] = jsonable(asdict(self.medium), nonfinite="text")
            d["medium"]["kind"] = "height_fog"
        elif self.medium is not None:
            d["medium"] = {"kind": "homogeneous", "beta": self.medium.beta}
        return d

    def view(self, name: str, camera: Camera, depth: np.ndarray) -> ViewHaze:
        """The haze of view ``name`` with z-depth ``depth`` (H, W) (inf = no surface)."""
        c = self.config
        norm = ray_norm(camera)
        distance = sanitize_depth(depth).astype(np.float64) * norm
        if c.mode == "onerestore":
            if c.sampling == "view":
                beta, airlight = self._draw(rng_for(self.seed, "haze", name))
            else:
                beta, airlight = self._scene_beta, self._scene_airlight
            t = onerestore_transmission(distance, beta, c.depth_cap, c.box_size, c.quantize_depth)
            normalise = InverseDepthNormalisation.of(distance)

            def particle_t(z: float) -> np.ndarray:
                d = np.minimum(1.0 - normalise(z * norm).astype(np.float64), c.depth_cap)
                return transmission_from_tau(_scaled(beta, d))
        else:
            beta, airlight = self._scene_beta, self._scene_airlight
            cap = c.max_distance if c.max_distance is not None else np.inf
            stride = max(1, -(-camera.width // max(1, c.fog_grid)))
            integrate = RayIntegrator(self.medium, camera, stride, c.fog_table_samples)
            t = transmission_from_tau(integrate(np.minimum(distance, cap)))

            def particle_t(z: float) -> np.ndarray:
                return transmission_from_tau(integrate(np.minimum(z * norm, cap)))

        info = {"beta": beta, "airlight": airlight.tolist(), "mean_transmission": float(t.mean())}
        return ViewHaze(t, airlight, beta, particle_t, info)

