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
import math
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

from nimbus.config_validation import (Limit, at_least, between, check_field, fraction, given_as, one_of, positive,
                                     validate)
from nimbus.errors import NimbusError
from weather_synth.archive import jsonable
from weather_synth.compose import COMPOSITION_ORDERS, ComposeConfig
from weather_synth.depth import ALIGN_METHODS, DepthConfig
from weather_synth.haze import HAZE_MODES, SAMPLING, HazeConfig
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
        # The sub-configs check their own cross-field rules; the table covers every number in the tree.
        for part in (self, self.haze, self.rain, self.snow, self.depth, self.compose):
            validate(part, LIMITS[type(part)])

    def to_dict(self) -> dict:
        return jsonable(dataclasses.asdict(self))


#: The accepted values of every field of the synthesizer's config tree, per config class
#: (see :mod:`nimbus.config_validation`); :meth:`SynthConfig.__post_init__` and ``--set`` check them.
LIMITS: dict[type, dict[str, Limit]] = {
    SynthConfig: {
        "seed": at_least(0, hi=math.inf), "max_wind_tilt": between(0, 90, hi_open=True, note="degrees"),
        "layer_compression": between(0, 9, note="zlib level"),
    },
    HazeConfig: {
        "mode": one_of(*HAZE_MODES), "sampling": one_of(*SAMPLING),
        "beta": at_least(0, finite=False, note="inf: opaque"), "beta_range": at_least(0, ordered=True),
        "visibility": positive(note="scene units"), "visibility_scale": positive(),
        "airlight": fraction(scalar=True, note="R, G, B"), "airlight_range": fraction(ordered=True),
        "depth_cap": at_least(0), "box_size": at_least(1, note="pixels; 1: no filter"),
        "max_distance": positive(note="scene units"),
        "fog_height_scale": positive(), "fog_noise_amplitude": fraction(), "fog_noise_scale": positive(),
        "fog_noise_octaves": at_least(1), "fog_far": positive(), "fog_grid": at_least(1),
        "fog_table_samples": at_least(1),
    },
    RainConfig: {
        "amount": at_least(0), "density_scale": at_least(0), "length_scale": at_least(0),
        "angle_jitter": between(0, 90, note="degrees"), "slices": at_least(1),
    },
    SnowConfig: {
        "amount": at_least(0), "size_scale": at_least(0), "color": fraction(), "slices": at_least(1),
    },
    DepthConfig: {
        "align": one_of(*ALIGN_METHODS),
        "min_points": at_least(2), "occlusion_window": fraction(note="of the image width"),
        "occlusion_tolerance": at_least(0), "guided_radius": fraction(note="of the image width"),
        "guided_eps": positive(), "input_size": at_least(14, note="pixels"),
        "recon_iterations": at_least(2), "recon_min_alpha": between(0, 1, lo_open=True, hi_open=True),
    },
    ComposeConfig: {"order": one_of(*COMPOSITION_ORDERS), "snow_color": fraction()},
}


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
    fall back to plain strings.  Each is checked against :data:`LIMITS` before it is
    set; unknown keys and bad values raise NimbusError naming the assignment as typed.
    """
    for item in assignments:
        if "=" not in item:
            raise NimbusError(f"--set expects key=value, got {item!r}")
        key, raw = item.split("=", 1)
        key, raw = key.strip(), raw.strip()
        config = _set_path(config, key.split("."), _parse_value(raw), key, raw)
    return config


def _parse_value(raw: str) -> Any:
    try:
        return json.loads(raw)
    except (json.JSONDecodeError, RecursionError):
        return raw


def _set_path(obj: Any, path: list[str], value: Any, full: str, raw: str) -> Any:
    names = {f.name: f for f in dataclasses.fields(obj)}
    head = path[0]
    if head not in names:
        raise NimbusError(f"unknown setting {full!r}; valid keys here: {', '.join(sorted(names))}")
    current = getattr(obj, head)
    if len(path) > 1:
        if not dataclasses.is_dataclass(current):
            raise NimbusError(f"{full!r}: {head} has no sub-settings")
        return replace(obj, **{head: _set_path(current, path[1:], value, full, raw)})
    if dataclasses.is_dataclass(current):
        raise NimbusError(f"{full!r} is a group of settings; set one of its keys, e.g. {full}.<key>")
    if isinstance(current, tuple) and current and dataclasses.is_dataclass(current[0]):
        raise NimbusError(f"{full!r} is a list of layer specs; change it in Python (or use the scale settings)")
    if isinstance(value, list):
        value = tuple(value)
    if isinstance(current, int) and not isinstance(current, bool) and isinstance(value, float) \
            and value.is_integer():
        value = int(value)  # JSON 1e3 or 3.0 for an integer field
    example = f"{full}={json.dumps(list(current))}" if isinstance(current, tuple) else None
    check_field(type(obj), head, value, LIMITS.get(type(obj), {}), given_as(full, raw), example)
    return replace(obj, **{head: value})
