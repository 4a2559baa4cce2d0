"""The synthesizer's whole configuration, its protocol presets and ``--set key=value`` overrides.

Protocols (:func:`protocol_config`):

``onerestore`` (default)
    Reproduces the NimbusGS paper's data: OneRestore haze on normalised depth
    with beta and airlight drawn per view, order rain -> snow -> haze, display
    values, particles without depth.
``physical``
    One homogeneous medium for the scene (``t = exp(-beta r)``, beta from
    ``--beta`` / ``--visibility`` or a visibility of 5 depth scales), particles
    with depth (size ~ 1/z, hidden behind surfaces, attenuated over their own
    distance), compositing in linear light.  ``--haze-mode heterogeneous``
    swaps in the world-space height fog.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np

from nimbus.errors import NimbusError
from weather_synth.archive import jsonable
from weather_synth.compose import ComposeConfig
from weather_synth.depth import DepthConfig
from weather_synth.haze import HazeConfig
from weather_synth.rain import RainConfig
from weather_synth.snow import SnowConfig

PROTOCOLS = ("onerestore", "physical")


@dataclass(frozen=True)
class SynthConfig:
    """Everything that decides a degraded dataset (recorded in its manifest).

    Attributes
    ----------
    protocol : str
        Name of the preset the config started from (informational).
    seed : int
        Scene seed; every random stream derives from it (:mod:`weather_synth.seeds`).
    haze, rain, snow, depth, compose : sub-configs
    depth_aware : bool
        Particles get depths (size ~ 1/z, occlusion by the scene).
    max_wind_tilt : float
        Rain and snow fall along the vertical tilted by ``U[0, max_wind_tilt]`` degrees
        (one wind per scene).
    layer_compression : int
        zlib level (0-9) of the per-view layer archives (1: float layers barely
        compress better at higher levels, and take several times longer).
    """

    protocol: str = "onerestore"
    seed: int = 0
    haze: HazeConfig = field(default_factory=HazeConfig)
    rain: RainConfig = field(default_factory=RainConfig)
    snow: SnowConfig = field(default_factory=SnowConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    compose: ComposeConfig = field(default_factory=ComposeConfig)
    depth_aware: bool = False
    max_wind_tilt: float = 15.0
    layer_compression: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.seed, (int, np.integer)) or isinstance(self.seed, bool) or self.seed < 0:
            raise NimbusError(f"seed must be a non-negative integer, got {self.seed!r}")
        if not 0 <= self.max_wind_tilt < 90:
            raise NimbusError(f"max wind tilt must be in [0, 90) degrees, got {self.max_wind_tilt}")
        if not 0 <= self.layer_compression <= 9:
            raise NimbusError(f"layer compression must be 0-9, got {self.layer_compression}")

    def to_dict(self) -> dict:
        return jsonable(dataclasses.asdict(self))


def protocol_config(protocol: str = "onerestore", seed: int = 0) -> SynthConfig:
    """The preset config of a protocol (module docstring)."""
    if protocol == "onerestore":
        return SynthConfig(protocol=protocol, seed=seed)
    if protocol == "physical":
        return SynthConfig(protocol=protocol, seed=seed, haze=HazeConfig(mode="homogeneous"),
                           compose=ComposeConfig(order="physical", linear=True), depth_aware=True)
    raise NimbusError(f"unknown protocol {protocol!r}; use one of {PROTOCOLS}")


def apply_overrides(config: SynthConfig, assignments: Sequence[str]) -> SynthConfig:
    """Apply ``key=value`` assignments (``haze.fog_noise_amplitude=0.3``, ``rain.slices=3``, ``seed=4``).

    Values are parsed as JSON (numbers, true/false, null, lists for tuples) and
    fall back to plain strings.  Unknown keys raise NimbusError listing the valid ones.
    """
    for item in assignments:
        if "=" not in item:
            raise NimbusError(f"--set expects key=value, got {item!r}")
        key, raw = item.split("=", 1)
        config = _set_path(config, key.strip().split("."), _parse_value(raw.strip()), key.strip())
    return config


def _parse_value(raw: str) -> Any:
    try:
        return json.loads(raw)
    except json.JSONDecodeError:
        return raw


def _set_path(obj: Any, path: list[str], value: Any, full: str) -> Any:
    names = {f.name: f for f in dataclasses.fields(obj)}
    head = path[0]
    if head not in names:
        raise NimbusError(f"unknown setting {full!r}; valid keys here: {', '.join(sorted(names))}")
    current = getattr(obj, head)
    if len(path) > 1:
        if not dataclasses.is_dataclass(current):
            raise NimbusError(f"{full!r}: {head} has no sub-settings")
        return replace(obj, **{head: _set_path(current, path[1:], value, full)})
    if dataclasses.is_dataclass(current):
        raise NimbusError(f"{full!r} is a group of settings; set one of its keys, e.g. {full}.<key>")
    if isinstance(value, list):
        value = tuple(value)
    if isinstance(current, tuple) and current and dataclasses.is_dataclass(current[0]):
        raise NimbusError(f"{full!r} is a list of layer specs; change it in Python (or use the scale settings)")
    if isinstance(current, bool) and not isinstance(value, bool):
        raise NimbusError(f"{full!r} expects true or false, got {value!r}")
    if isinstance(current, (int, float)) and not isinstance(current, bool) and not isinstance(value, (int, float)):
        raise NimbusError(f"{full!r} expects a number, got {value!r}")
    if isinstance(current, int) and not isinstance(current, bool) and isinstance(value, float):
        if not value.is_integer():
            raise NimbusError(f"{full!r} expects an integer, got {value!r}")
        value = int(value)
    try:
        return replace(obj, **{head: value})
    except TypeError as e:
        raise NimbusError(f"{full!r}: {e}") from None

