"""Per-view z-depth from a quick 3DGS fit to the clean views (the ``recon`` depth source of ``nimbus-synth``).

Haze synthesis needs a depth map per view.  Scenes without depth maps used to
get one by densifying the sparse SfM points view by view, which leaves each view
with its own guesses between the points (clear air in front of far walls, haze
in front of near objects).  Here one set of Gaussians is fitted to *all* the
views (train and test: every view is degraded, and the clean images are the
input of synthesis, not a benchmark's held-out truth), and each view's depth is
rendered from that one model, so the depth maps of different views describe the
same surfaces: multi-view consistent by construction.

Depth per pixel is the rasterizer's expected z over the accumulated opacity,
``sum z_i a_i T_i / sum a_i T_i``; pixels whose opacity stays below
:attr:`ReconDepthConfig.min_alpha` see no surface and get ``inf`` (the sky,
as the synthesizer's depth maps write it).

Results are cached by content (:func:`recon_cache_key`: the views' image bytes,
cameras and names, the sparse points, the settings and :data:`RECON_VERSION`),
one ``.npz`` per scene and settings, so a second ``degrade`` of the same scene
reuses the fit.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from nimbus.data import Scene
from nimbus.errors import NimbusError
from nimbus.render.rasterize import rasterize
from nimbus.train.config import TrainConfig, preset
from nimbus.train.runner import Runner
from nimbus.utils.fs import atomic_write_bytes

#: Part of the cache key: bump when the fit or the depth render changes what a cached file holds.
RECON_VERSION = 1
#: Fewest views a fit is attempted on: with fewer, 3DGS fits each image with a flat card and depth means nothing.
MIN_RECON_VIEWS = 3
#: Progress lines per fit (one every 1/N of the iterations).
PROGRESS_LINES = 5


@dataclass(frozen=True)
class ReconDepthConfig:
    """How the quick fit is run.

    Attributes
    ----------
    preset : str
        3DGS preset the schedule comes from (:data:`nimbus.train.config.PRESETS`).
    iterations : int
        Length of the fit; the preset's schedule is rescaled to it
        (:meth:`TrainConfig.rescaled`).  The default, 600 (the ``tiny`` schedule
        stretched twice), measured on the tiny built-in scenes without their
        depth maps (``tools/speed/depth.py``): 300 -> 600 iterations raised
        garden's depth consistency 0.867 -> 0.882 and its share of pixels within
        5 % of the exact depth 0.48 -> 0.52 (street: 0.953 -> 0.947, 0.41 -> 0.42);
        1000 added under 0.01 to either for 1.7 times the time.
    min_alpha : float
        Pixels whose accumulated opacity is below this see no surface: ``inf`` depth.
    seed : int
        Seed of the fit (same scene, settings and seed: same depth on one machine).
    backend : str
        Rasterizer backend (``auto``, ``cpp``, ``torch``, ``gsplat``).
    """

    preset: str = "tiny"
    iterations: int = 600
    min_alpha: float = 0.5
    seed: int = 0
    backend: str = "auto"

    def __post_init__(self) -> None:
        preset(self.preset)  # an unknown name raises NimbusError listing the known ones
        if self.iterations < 2:
            raise NimbusError(f"recon depth iterations must be >= 2, got {self.iterations}")
        if not 0 < self.min_alpha < 1:
            raise NimbusError(f"recon depth min_alpha must be in (0, 1), got {self.min_alpha}")

    def train_config(self) -> TrainConfig:
        """The trainer config of the fit: the preset rescaled to ``iterations``, no checkpoints in between."""
        cfg = preset(self.preset)
        if self.iterations != cfg.iterations:
            cfg = cfg.rescaled(self.iterations)
        return dataclasses.replace(cfg, backend=self.backend, checkpoint_interval=10**9,
                                   log_interval=max(1, self.iterations // PROGRESS_LINES))


@dataclass(frozen=True)
class ReconDepth:
    """Per-view depth maps of one fit.

    Attributes
    ----------
    depths : dict
        View name -> z-depth float32 (H, W), scene units, ``inf`` = no surface.
    info : dict
        ``key`` (cache key), ``iterations``, ``gaussians``, ``psnr`` (mean over the
        views, dB), ``fit_seconds``, ``cached`` (True when read from the cache).
    """

    depths: dict
    info: dict


@torch.no_grad()
def render_depth(gaussians, camera, min_alpha: float = 0.5, backend: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Expected z-depth (H, W) float32 (``inf`` where the opacity is below ``min_alpha``) and the opacity (H, W)."""
    _, depth, alpha, _ = rasterize(gaussians, camera, backend=backend)
    depth, alpha = depth.double().cpu().numpy(), alpha.double().cpu().numpy()
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(alpha >= min_alpha, depth / np.maximum(alpha, 1e-12), np.inf)
    return z.astype(np.float32), alpha.astype(np.float32)


def recon_cache_key(scene: Scene, config: ReconDepthConfig = ReconDepthConfig()) -> str:
    """sha256 over what the fit depends on: each view's name, camera and image, the sparse points, the settings."""
    h = hashlib.sha256()
    h.update(json.dumps({"recon_version": RECON_VERSION, "config": dataclasses.asdict(config)},
                        sort_keys=True).encode())
    for v in scene.views:
        cam = v.camera
        h.update(v.name.encode() + b"\0")
        h.update(np.asarray([cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy], np.float64).tobytes())
        h.update(np.asarray(cam.world_to_camera, np.float64).tobytes())
        h.update(np.ascontiguousarray(v.load_image(), np.float32).tobytes())
    h.update(np.ascontiguousarray(scene.points, np.float64).tobytes())
    h.update(np.ascontiguousarray(scene.colors, np.uint8).tobytes())
    return h.hexdigest()


def check_recon_possible(scene: Scene) -> None:
    """Raise NimbusError when a fit cannot give meaningful depth (too few views)."""
    if len(scene.views) < MIN_RECON_VIEWS:
        raise NimbusError(f"--depth recon fits 3DGS to the views and needs at least {MIN_RECON_VIEWS}, the scene has "
                          f"{len(scene.views)}; use --depth scene (depth maps), sparse or onnx:MODEL.onnx")


def fit_recon_depth(scene: Scene, config: ReconDepthConfig = ReconDepthConfig(),
                    work_dir: str | os.PathLike | None = None,
                    log: Callable[[str], None] | None = None) -> ReconDepth:
    """Fit 3DGS to every view of ``scene`` and render each view's z-depth (no cache; see :func:`recon_depth`).

    ``work_dir`` holds the trainer's run folder while it runs (removed after);
    default: the system's temporary folder.  ``log`` receives progress lines.
    """
    check_recon_possible(scene)
    say = log or (lambda line: None)
    cfg = config.train_config()
    every = scene.with_split(())
    run = Path(tempfile.mkdtemp(prefix=".recon-fit.tmp-", dir=work_dir))
    say(f"recon depth: fitting 3DGS to {len(every.views)} views ({config.preset} schedule, {cfg.iterations} "
        f"iterations)")

    def progress(rec: dict) -> None:
        say(f"recon depth: iteration {rec['iteration']}/{cfg.iterations}, PSNR {rec['psnr']:.2f} dB, "
            f"{rec['gaussians']} Gaussians")

    start = time.perf_counter()
    try:
        # 3DGS through the runner, stopped at the fitted Gaussians: a cache fit is never resumed, so
        # checkpoints, evaluation, renders and PLY would only cost time; the loop and guards are the runner's.
        runner = Runner("3dgs", every, cfg, run, seed=config.seed, progress=False, checkpoints=False,
                        on_log=progress)
        runner.train()
        g = runner.gaussians().detach()
        depths, psnrs = {}, []
        for view in every.views:
            z, _ = render_depth(g, view.camera, config.min_alpha, config.backend)
            depths[view.name] = z
        last = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]
        psnrs = [r["psnr"] for r in last if "psnr" in r]
    finally:
        shutil.rmtree(run, ignore_errors=True)
    seconds = time.perf_counter() - start
    info = {"iterations": cfg.iterations, "gaussians": runner.method.num_gaussians,
            "psnr": psnrs[-1] if psnrs else None, "fit_seconds": round(seconds, 3), "cached": False}
    say(f"recon depth: fitted in {seconds:.1f} s ({info['gaussians']} Gaussians)")
    return ReconDepth(depths, info)


def _read_cache(path: Path, scene: Scene) -> ReconDepth | None:
    """The cached depths at ``path`` when the file is whole and fits ``scene``, else None (refit)."""
    try:
        with np.load(path, allow_pickle=False) as f:
            info = json.loads(bytes(f["__info__"]).decode())
            depths = {v.name: np.asarray(f[f"d{i}"], np.float32) for i, v in enumerate(scene.views)}
    except (OSError, KeyError, ValueError, EOFError):
        return None
    for v in scene.views:
        if depths[v.name].shape != (v.camera.height, v.camera.width):
            return None
    return ReconDepth(depths, {**info, "cached": True})


def recon_depth(scene: Scene, config: ReconDepthConfig = ReconDepthConfig(),
                cache_dir: str | os.PathLike | None = None,
                log: Callable[[str], None] | None = None) -> ReconDepth:
    """Per-view depth of ``scene`` from a fit, read from ``cache_dir`` when an equal fit is cached there.

    Parameters
    ----------
    scene : Scene
    config : ReconDepthConfig
    cache_dir : path, optional
        Folder of the cache (created); ``recon-<key>.npz`` per scene and settings.
        None: fit every time.
    log : callable, optional
        Receives progress lines (the fit's, or that the cache was used).
    """
    say = log or (lambda line: None)
    check_recon_possible(scene)
    key = recon_cache_key(scene, config)
    path = None if cache_dir is None else Path(cache_dir) / f"recon-{key[:32]}.npz"
    if path is not None and path.is_file():
        got = _read_cache(path, scene)
        if got is not None:
            say(f"recon depth: using the cached fit {path}")
            return ReconDepth(got.depths, {**got.info, "key": key})
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
    result = fit_recon_depth(scene, config, path.parent if path is not None else None, log)
    info = {**result.info, "key": key}
    if path is not None:
        buf = io.BytesIO()
        arrays = {f"d{i}": result.depths[v.name] for i, v in enumerate(scene.views)}
        np.savez_compressed(buf, __info__=np.frombuffer(json.dumps(info).encode(), np.uint8), **arrays)
        atomic_write_bytes(path, buf.getvalue())
    return ReconDepth(result.depths, info)
