"""The synthesizer's whole configuration and its protocol presets (``--set``: :mod:`nimbus.config_set`).

Protocols (:func:`protocol_config`; :data:`PROTOCOL_SUMMARIES` says each in one line):

``onerestore`` (default)
    Reproduces the NimbusGS paper's data: OneRestore haze on normalised depth
    with beta and airlight drawn per view, order rain -> snow -> haze, display
    values, particles without depth.  Drawn per view, the haze is not one medium
    the views share: two views of a point see it through different haze.
``physical``
    One homogeneous medium for the scene, the same for every view (view-consistent
    haze): ``t = exp(-beta r)`` with beta from ``--beta`` / ``--visibility`` or a
    visibility of 5 depth scales; particles with depth (size ~ 1/z, hidden behind
    surfaces, attenuated over their own distance), compositing in linear light.
    ``--haze-mode heterogeneous`` swaps in the world-space height fog.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import ClassVar

from nimbus.config_validation import Limit, at_least, between, validate
from nimbus.errors import NimbusError
from nimbus.utils.jsonable import jsonable
from weather_synth.compose import ComposeConfig
from weather_synth.depth import DepthConfig
from weather_synth.haze import HazeConfig
from weather_synth.rain import RainConfig
from weather_synth.snow import SnowConfig

PROTOCOLS = ("onerestore", "physical")
#: What each protocol draws per view and per scene, in one line (``--help``, the benchmark's tables).
PROTOCOL_SUMMARIES = {
    "onerestore": "the paper's data: haze beta and airlight drawn per view on normalised depth (not one medium "
                  "across views), particles per view",
    "physical": "one medium per scene (one beta and airlight, t = exp(-beta * distance): view-consistent haze), "
                "depth-aware particles, linear light",
}


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

    #: The accepted values of this level's fields; each sub-config keeps its own (:mod:`nimbus.config_validation`).
    LIMITS: ClassVar[dict[str, Limit]] = {
        "seed": at_least(0, hi=math.inf), "max_wind_tilt": between(0, 90, hi_open=True, note="degrees"),
        "layer_compression": between(0, 9, note="zlib level"),
    }

    def __post_init__(self) -> None:
        # The sub-configs check their own cross-field rules; the tables cover every number in the tree.
        validate(self)

    def to_dict(self) -> dict:
        return jsonable(dataclasses.asdict(self), nonfinite="text")


def protocol_config(protocol: str = "onerestore", seed: int = 0) -> SynthConfig:
    """The preset config of a protocol (module docstring)."""
    if protocol == "onerestore":
        return SynthConfig(protocol=protocol, seed=seed)
    if protocol == "physical":
        return SynthConfig(protocol=protocol, seed=seed, haze=HazeConfig(mode="homogeneous"),
                           compose=ComposeConfig(order="physical", linear=True), depth_aware=True)
    raise NimbusError(f"unknown protocol {protocol!r}; use one of {PROTOCOLS}")
