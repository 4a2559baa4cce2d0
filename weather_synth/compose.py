"""Composite the clean image, the haze and the particle slices into the degraded image.

Orders (:attr:`ComposeConfig.order`):

``"onerestore"``
    OneRestore's fixed order rain -> snow -> haze, i.e.
    ``I = clip(((J + R) (1 - S) + C S) t + A (1 - t))`` with ``R`` the summed
    rain slices and ``S = 1 - prod(1 - S_k)`` the union of the snow masks:
    particles sit *behind* the haze, attenuated by the full scene transmission.
``"physical"``
    Each particle attenuated only over its own distance.  With ``T_k`` the
    transmission from the camera to slice k (depth ``z_k``), start from the hazy
    scene ``J t + A (1 - t)`` and apply slices far to near:
    rain ``I += R_k T_k`` (the drop's light crosses ``z_k`` of medium) and snow
    ``I = I (1 - S_k) + S_k (C T_k + A (1 - T_k))`` (a flake is an opaque
    surface at ``z_k`` seen through the haze).  Composing the segment
    transmissions shows this equals the radiative transfer along the ray.
    Slices at ``z = 0`` (not depth-aware) are unattenuated.

``linear=True`` composites in linear light: image, airlight and snow colour are
decoded with the sRGB transfer function (``colour.cctf_decoding``), the rain
layer is radiance added in linear light, and the result is re-encoded
(``colour.cctf_encoding``).  The default works on display values, as OneRestore.

When nothing changes a pixel (no rain, no snow, ``t = 1``), the input comes
back bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from nimbus.config_validation import Limit, fraction, one_of
from nimbus.errors import NimbusError
from weather_synth.haze import ViewHaze
from weather_synth.particles import ParticleSlice

COMPOSITION_ORDERS = ("onerestore", "physical")


@dataclass(frozen=True)
class ComposeConfig:
    """How layers are composited.

    Attributes
    ----------
    order : str
        ``"onerestore"`` or ``"physical"`` (module docstring).
    linear : bool
        Composite in linear light instead of display (sRGB-encoded) values.
    snow_color : float
        Snow colour ``C`` (display value).
    """

    order: str = "onerestore"
    linear: bool = False
    snow_color: float = 1.0

    #: The accepted values of each field (see :mod:`nimbus.config_validation`).
    LIMITS: ClassVar[dict[str, Limit]] = {
        "order": one_of(*COMPOSITION_ORDERS), "snow_color": fraction(),
    }

    def __post_init__(self) -> None:
        if self.order not in COMPOSITION_ORDERS:
            raise NimbusError(f"unknown composition order {self.order!r}; use one of {COMPOSITION_ORDERS}")


def srgb_decode(x: np.ndarray) -> np.ndarray:
    """Display sRGB values -> linear light (colour-science's sRGB EOTF), float32."""
    import colour

    return np.asarray(colour.cctf_decoding(np.asarray(x, np.float64), function="sRGB"), np.float32)


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """Linear light -> display sRGB values (colour-science's inverse EOTF), float32."""
    import colour

    return np.asarray(colour.cctf_encoding(np.asarray(x, np.float64), function="sRGB"), np.float32)


def compose(clean: np.ndarray, haze: ViewHaze | None, slices: list[ParticleSlice],
            config: ComposeConfig = ComposeConfig()) -> np.ndarray:
    """The degraded image, float32 (H, W, 3) in [0, 1].

    Parameters
    ----------
    clean : ndarray, (H, W, 3), float32 in [0, 1]
    haze : ViewHaze or None
        None (or ``t = 1`` everywhere) for no haze.
    slices : list of ParticleSlice
        Rain (additive) and snow (alpha) slices; empty ones are ignored.
    config : ComposeConfig
    """
    J = np.asarray(clean, np.float32)
    rain = [s for s in slices if s.kind == "rain" and np.any(s.layer > 0)]
    snow = [s for s in slices if s.kind == "snow" and np.any(s.layer > 0)]
    hazy = haze is not None and not np.all(haze.transmission == 1)
    if not (rain or snow or hazy):
        return J
    A = haze.airlight if haze is not None else np.zeros(3, np.float32)
    C = np.float32(config.snow_color)
    if config.linear:
        J, A, C = srgb_decode(J), srgb_decode(A), np.float32(srgb_decode(np.array([C]))[0])
    one = np.float32(1)
    if config.order == "onerestore":
        I = J
        if rain:
            I = I + sum(s.layer for s in rain)[..., None]
        if snow:
            keep = np.ones(J.shape[:2], np.float32)
            for s in snow:
                keep *= one - np.clip(s.layer, 0, 1)
            S = (one - keep)[..., None]
            I = I * (one - S) + C * S
        if hazy:
            t = haze.transmission[..., None]
            I = I * t + A * (one - t)
    else:
        if hazy:
            t = haze.transmission[..., None]
            I = J * t + A * (one - t)
        else:
            I = J
        for s in sorted(rain + snow, key=lambda s: -s.z):
            T = haze.particle_transmission(s.z)[..., None] if (hazy and s.z > 0) else one
            layer = s.layer[..., None]
            if s.kind == "rain":
                I = I + layer * T
            else:
                a = np.clip(layer, 0, 1)
                I = I * (one - a) + a * (C * T + A * (one - T))
    I = np.clip(np.nan_to_num(I, nan=1.0, posinf=1.0), 0, 1)
    if config.linear:
        I = np.clip(srgb_encode(I), 0, 1)
    return I.astype(np.float32)
