"""Degrade one view of a scene: the scene-level models (depth, haze, wind) and the per-view layers.

:class:`Synthesizer` holds what is shared by all views of a scene (the depth
source and depth scale, the haze medium or sampling, the wind) and degrades
one view at a time for a :class:`~weather_synth.settings.WeatherSetting`.
A view's layers depend only on the seed, the view and the layer kind, never on
the setting: ``H+R`` of a view is exactly its ``H`` transmission and its ``R``
streaks composited together.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nimbus.data.images import read_depth, write_depth
from nimbus.data.scene import Scene, View
from nimbus.errors import NimbusError
from weather_synth.compose import compose
from weather_synth.config import SynthConfig
from weather_synth.depth import DepthSource, depth_scale
from weather_synth.haze import HazeModel
from weather_synth.medium import estimate_up
from weather_synth.particles import ParticleSlice, coverage, fall_direction
from weather_synth.rain import render_rain
from weather_synth.seeds import derive_seed, rng_for
from weather_synth.settings import WeatherSetting
from weather_synth.snow import render_snow

# A particle pixel counts as covered above this layer value (rain radiance / snow alpha).
COVERAGE_THRESHOLD = 0.01
# Estimated depths are cached in ``<cache_parent>/.depth-cache.tmp-*``: the naming and ``.owner`` pid file of
# nimbus.utils.fs.atomic_dir, so remove_stale_temps(<cache_parent>/depth-cache) removes one a killed run left.
DEPTH_CACHE_NAME = "depth-cache"


@dataclass
class ViewResult:
    """A degraded view.

    Attributes
    ----------
    image : ndarray, (H, W, 3), float32 in [0, 1]
    layers : dict of str -> ndarray
        Ground-truth layers of the setting's components (see :func:`layer_arrays`).
    info : dict
        JSON-able per-view values (seeds, sampled parameters, statistics).
    mean_transmission : float or None
        None without haze.
    particle_coverage : float
        Fraction of pixels covered by rain or snow.
    """

    image: np.ndarray
    layers: dict
    info: dict
    mean_transmission: float | None
    particle_coverage: float


def flatten_slices(slices: list[ParticleSlice], shape: tuple[int, int], kind: str) -> tuple[np.ndarray, np.ndarray]:
    """One layer and one depth map per particle kind.

    Rain: the sum of the slices; snow: the union of the alphas ``1 - prod(1 - S_k)``.
    Depth: z of the slice contributing most at each pixel (``inf`` where there is
    none; 0 for particles without depth).
    """
    layer = np.zeros(shape, np.float32)
    best = np.zeros(shape, np.float32)
    depth = np.full(shape, np.inf, np.float32)
    keep = np.ones(shape, np.float32)
    for s in slices:
        if kind == "rain":
            layer += s.layer
        else:
            keep *= 1 - np.clip(s.layer, 0, 1)
        win = s.layer > best
        best = np.where(win, s.layer, best)
        depth = np.where(win, np.float32(s.z), depth)
    if kind == "snow":
        layer = 1 - keep
    return layer, depth


def scene_up(scene: Scene) -> np.ndarray | None:
    """The world up direction a scene declares (built-in scenes: ``conventions.world_up`` in their
    metadata or their folder's ``manifest.json``), or None."""
    meta = scene.metadata if isinstance(scene.metadata, dict) else {}
    if "conventions" not in meta and scene.root is not None and (Path(scene.root) / "manifest.json").is_file():
        try:
            meta = json.loads((Path(scene.root) / "manifest.json").read_text())
        except (OSError, json.JSONDecodeError):
            meta = {}
    up = meta.get("up", (meta.get("conventions") or {}).get("world_up")) if isinstance(meta, dict) else None
    try:
        up = np.asarray(up, np.float64).reshape(3)
    except (TypeError, ValueError):
        return None
    n = np.linalg.norm(up)
    return up / n if np.isfinite(n) and n > 0 else None


class Synthesizer:
    """Scene-level weather models; :meth:`degrade` makes one view's degraded image and layers.

    Parameters
    ----------
    scene : Scene
    config : SynthConfig
    cache_parent : path, optional
        Folder to keep the depth cache in (``degrade_scene`` passes its output
        folder, so a run writes nowhere else); default: the system's temp folder.

    Use as a context manager (or call :meth:`close`): depths estimated from
    sparse points or a network are cached in a temporary folder for the run so
    that every setting reuses them.
    """

    def __init__(self, scene: Scene, config: SynthConfig, cache_parent: str | os.PathLike | None = None) -> None:
        if not scene.views:
            raise NimbusError("the scene has no views; nothing to degrade")
        self.scene = scene
        self.config = config
        self.seed = int(config.seed)
        cams = [v.camera for v in scene.views]
        up = scene_up(scene)
        self.up = up if up is not None else estimate_up(cams)
        self.origin = np.mean([c.center for c in cams], axis=0)
        wind = rng_for(self.seed, "wind")
        self.wind_tilt = float(wind.uniform(0, config.max_wind_tilt))
        self.wind_azimuth = float(wind.uniform(0, 360))
        self.fall_dir = fall_direction(self.up, self.wind_tilt, self.wind_azimuth)
        self._depth_source: DepthSource | None = None
        self._depth_scale: float | None = None
        self._haze: HazeModel | None = None
        self._cache_dir: Path | None = None
        self._cache_parent = None if cache_parent is None else Path(cache_parent)

    # --- lazily built scene-level models -----------------------------------------------------
    @property
    def depth_source(self) -> DepthSource:
        if self._depth_source is None:
            self._depth_source = DepthSource(self.scene, self.config.depth)
        return self._depth_source

    @property
    def depth_scale(self) -> float:
        if self._depth_scale is None:
            self._depth_scale = depth_scale(self.scene, self.depth_source)
        return self._depth_scale

    @property
    def haze(self) -> HazeModel:
        if self._haze is None:
            needs_scale = self.config.haze.physical
            self._haze = HazeModel(self.config.haze, self.seed, self.depth_scale if needs_scale else 1.0,
                                   self.up, self.origin)
        return self._haze

    def needs_depth(self, setting: WeatherSetting) -> bool:
        return setting.haze or (self.config.depth_aware and (setting.rain or setting.snow))

    def prepare(self, settings: list[WeatherSetting]) -> None:
        """Build the models the settings need now, so bad input fails before anything is written."""
        if any(self.needs_depth(s) for s in settings):
            _ = self.depth_source
            if self.config.depth_aware or self.config.haze.physical:
                _ = self.depth_scale
        if any(s.haze for s in settings):
            _ = self.haze

    def depth(self, view: View, image: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
        """The view's z-depth (cached for expensive sources) and its info."""
        src = self.depth_source
        if src.kind == "scene":
            return src(view, image)
        if self._cache_dir is None:
            if self._cache_parent is None:
                self._cache_dir = Path(tempfile.mkdtemp(prefix="nimbus-synth-depth-"))
            else:
                self._cache_parent.mkdir(parents=True, exist_ok=True)
                self._cache_dir = Path(tempfile.mkdtemp(prefix=f".{DEPTH_CACHE_NAME}.tmp-", dir=self._cache_parent))
                (self._cache_dir / ".owner").write_text(str(os.getpid()))
        key = str(derive_seed(0, "depth-cache", view.name))
        f = self._cache_dir / f"{key}.npy"
        info_f = self._cache_dir / f"{key}.json"
        if f.is_file():
            return read_depth(f), json.loads(info_f.read_text())
        depth, info = src(view, image)
        write_depth(f, depth)
        info_f.write_text(json.dumps(info))
        return depth, info

    def close(self) -> None:
        if self._cache_dir is not None:
            shutil.rmtree(self._cache_dir, ignore_errors=True)
            self._cache_dir = None

    def __enter__(self) -> "Synthesizer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def uses_depth_scale(self, setting: WeatherSetting) -> bool:
        """Whether ``setting``'s layers depend on :attr:`depth_scale`: one-medium (physical) haze, and
        depth-aware rain or snow."""
        return ((setting.haze and self.config.haze.physical)
                or (self.config.depth_aware and (setting.rain or setting.snow)))

    def describe(self, setting: WeatherSetting | None = None) -> dict:
        """Scene-level values for the manifest: of ``setting`` only what it used (its depth source,
        depth scale and haze model), so a setting's manifest does not depend on which other settings
        were synthesised in the same call; without ``setting``, everything built so far."""
        d = {
            "seed": self.seed,
            "up": self.up.tolist(),
            "wind": {"tilt_deg": self.wind_tilt, "azimuth_deg": self.wind_azimuth,
                     "fall_direction": self.fall_dir.tolist()},
        }
        if self._depth_source is not None and (setting is None or self.needs_depth(setting)):
            d["depth"] = self._depth_source.describe()
        if self._depth_scale is not None and (setting is None or self.uses_depth_scale(setting)):
            d["depth_scale"] = self._depth_scale
        if self._haze is not None and (setting is None or setting.haze):
            d["haze"] = self._haze.describe()
        return d

    # --- one view --------------------------------------------------------------------------
    def degrade(self, view: View, setting: WeatherSetting, image: np.ndarray | None = None) -> ViewResult:
        """Degrade ``view`` for ``setting``; ``image`` is its clean image if already loaded."""
        cfg = self.config
        J = view.load_image() if image is None else image
        cam = view.camera
        shape = (cam.height, cam.width)
        info: dict = {"seeds": {}}
        layers: dict = {}
        depth = None
        if self.needs_depth(setting):
            depth, dinfo = self.depth(view, J)
            if dinfo:
                info["depth"] = dinfo
        haze = None
        if setting.haze:
            haze = self.haze.view(view.name, cam, depth)
            info["seeds"]["haze"] = derive_seed(self.seed, "haze", view.name)
            info["haze"] = haze.info
            layers.update(transmission=haze.transmission, airlight=haze.airlight)
            if self.depth_source.kind != "scene":
                layers["depth"] = depth  # estimated: not in the scene's own depths/
        slices: list[ParticleSlice] = []
        scale = self.depth_scale if cfg.depth_aware else 1.0
        for kind, on, render, sub in (("rain", setting.rain, render_rain, cfg.rain),
                                      ("snow", setting.snow, render_snow, cfg.snow)):
            if not on:
                continue
            info["seeds"][kind] = derive_seed(self.seed, kind, view.name)
            res = render(cam, rng_for(self.seed, kind, view.name), sub, self.fall_dir, depth, scale, cfg.depth_aware)
            slices += res.slices
            info[kind] = res.info
            layer, zmap = flatten_slices(res.slices, shape, kind)
            layers[kind] = layer
            layers[f"{kind}_depth"] = zmap
            info[kind]["coverage"] = coverage(res.slices, shape, COVERAGE_THRESHOLD)
        out = compose(J, haze, slices, cfg.compose)
        t_mean = float(haze.transmission.mean()) if haze is not None else None
        cov = coverage(slices, shape, COVERAGE_THRESHOLD)
        info["mean_transmission"] = t_mean
        info["particle_coverage"] = cov
        return ViewResult(out, layers, info, t_mean, cov)
