"""The decomposition check: a medium-modelling run's learned layers against the synthesiser's ground truth.

``nimbus-synth degrade`` keeps every layer it composed a training view from (:mod:`weather_synth.dataset`):
the clean view ``J`` (``clean/``), the transmission ``t`` and airlight ``A`` (``layers/NAME.npz``), the depth
the haze was made from and the sky mask.  A method that models a medium learns the same three things:

NimbusGS (``nimbus``, ``nimbus-full``, ``nimbus-paper`` and the ablations with CSM)
    ``render(camera, view_index=i)`` gives the clean render ``I_hat``, the transmission ``T`` [H, W, 1] and the
    scattered light ``P`` [H, W, 3] (``I_con = I_hat T + P``): its effective airlight is ``P / (1 - T)``.
medium-3dgs
    the same call gives ``I_hat`` (``rgb``), a per-channel ``transmission`` ``alpha exp(-sigma_attn z)``
    [H, W, 3] and ``backscatter`` ``B (1 - alpha exp(-sigma_bs z))`` [H, W, 3], taken as ``T`` and ``P``.

:func:`decompose_run` re-renders every training view of a finished run (read-only, through
:meth:`~nimbus.train.runner.Runner.open`: ``config.json`` and ``checkpoint.pt`` read with
``torch.load(weights_only=True)``) and compares it with the layers of the setting folder its
``config.json`` names, pooled over the views per depth band.

Bands
-----
``sky`` is every pixel the sky mask marks (or whose depth is not finite).  The other pixels are
surface pixels; their ray distance (the synthesiser's z-depth times the pixel ray's length) is cut
into ``near`` / ``middle`` / ``far``, the thirds of its range over every training view's surface
pixels (equal widths, not quantiles: the far band may hold few pixels, and ``pixels`` says so).
``all`` pools the four.  Pixels a validity mask (``masks/``) leaves out are left out here too.

Figures per band (each pixel of each view weighs the same; errors are learned minus true)
------------------------------------------------------------------------------------------
``t_bias``, ``t_mae``
    mean of ``T - t`` and of ``|T - t|`` (a per-channel ``T`` is averaged over the channels first).
``airlight_learned``, ``airlight_true``, ``airlight_error`` (R, G, B), ``airlight_bias``
    the effective airlight as a ratio of sums, ``sum P / sum (1 - T)`` per channel, against the
    views' true airlight weighted alike, ``sum (1 - T) A / sum (1 - T)``: the ``(1 - T)``-weighted
    mean of ``P / (1 - T) - A``, so pixels the learned medium barely veils (``T`` near 1, where
    ``P / (1 - T)`` is noise over nothing) weigh little and nothing is divided by zero.  None where
    the learned medium veils nothing in the band.  ``airlight_bias`` is the mean over the channels.
``clean_bias`` (R, G, B), ``mse``, ``mse_share``
    mean of ``I_hat - J`` per channel (``I_hat`` clipped to [0, 1], as a saved render is), the mean
    squared error, and the band's share of the summed squared error of every pixel.
``psnr``, ``psnr_offset_removed``, ``veil_gain_db``
    PSNR (peak 1) of ``I_hat`` against ``J``, the same after subtracting the band's ``clean_bias``
    from ``I_hat``, and their difference: how much of the error is a flat per-channel offset, the
    veil of haze a clean render kept (or took away twice).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nimbus.errors import NimbusError

FORMAT = "nimbus-bench-decompose/1"
#: Depth bands, in table order; :data:`ALL` pools them.
BANDS = ("near", "middle", "far", "sky")
ALL = "all"
#: The record and table files ``nimbus-bench decompose`` writes, and its default folder inside the run.
RECORD = "decompose.json"
MARKDOWN = "decompose.md"
DEFAULT_DIR = "decompose"
#: Below this much summed ``1 - T`` per pixel of a band the learned medium veils nothing there: no airlight.
MIN_VEIL = 1e-4
#: Which extras of ``render(camera, view_index=i)`` are T and P, by the key of P (see the module docstring).
SCATTERED_KEYS = ("airlight", "backscatter")
#: Methods that model a medium (the error message lists them).
MEDIUM_METHODS = "nimbus, nimbus-full, nimbus-paper, the NimbusGS ablations with CSM, medium-3dgs"


@dataclass
class BandSums:
    """Running sums of one band over the views (float64), from which :meth:`record` makes the figures."""

    pixels: int = 0
    t_true: float = 0.0
    t_learned: float = 0.0
    t_abs: float = 0.0
    veil: np.ndarray = field(default_factory=lambda: np.zeros(3))  # sum (1 - T) per channel
    scattered: np.ndarray = field(default_factory=lambda: np.zeros(3))  # sum P
    veiled_airlight: np.ndarray = field(default_factory=lambda: np.zeros(3))  # sum (1 - T) A
    err: np.ndarray = field(default_factory=lambda: np.zeros(3))  # sum (I_hat - J)
    err2: np.ndarray = field(default_factory=lambda: np.zeros(3))  # sum (I_hat - J)^2

    def add(self, sel: np.ndarray, T: np.ndarray, t: np.ndarray, P: np.ndarray, A: np.ndarray,
            clean: np.ndarray, truth: np.ndarray) -> None:
        """Add the pixels ``sel`` (bool [H, W]) of one view: learned ``T`` [H, W, C] (C = 1 or 3), true ``t``
        [H, W], learned ``P`` [H, W, 3], true ``A`` [3], ``clean`` (I_hat) and ``truth`` (J) [H, W, 3]."""
        T, P, clean, truth = T[sel], P[sel], clean[sel], truth[sel]
        T3 = np.broadcast_to(T, P.shape)
        self.pixels += int(sel.sum())
        self.t_true += float(t[sel].sum())
        self.t_learned += float(T.mean(-1).sum())
        self.t_abs += float(np.abs(T.mean(-1) - t[sel]).sum())
        self.veil += (1.0 - T3).sum(0)
        self.scattered += P.sum(0)
        self.veiled_airlight += (1.0 - T3).sum(0) * A
        e = clean - truth
        self.err += e.sum(0)
        self.err2 += (e * e).sum(0)

    def __iadd__(self, other: "BandSums") -> "BandSums":
        for name in ("pixels", "t_true", "t_learned", "t_abs", "veil", "scattered", "veiled_airlight", "err", "err2"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        return self

    def record(self, total_pixels: int, total_err2: float) -> dict:
        """The band's figures (module docstring); None for what an empty band has no value of."""
        n = self.pixels
        out: dict = {"pixels": n, "pixel_share": n / total_pixels if total_pixels else None}
        if n == 0:
            return {**out, **{k: None for k in ("t_true", "t_learned", "t_bias", "t_mae", "airlight_learned",
                                                "airlight_true", "airlight_error", "airlight_bias", "clean_bias",
                                                "mse", "mse_share", "psnr", "psnr_offset_removed", "veil_gain_db")}}
        out.update(t_true=self.t_true / n, t_learned=self.t_learned / n, t_bias=(self.t_learned - self.t_true) / n,
                   t_mae=self.t_abs / n)
        if (self.veil > MIN_VEIL * n).all():
            learned, true = self.scattered / self.veil, self.veiled_airlight / self.veil
            out.update(airlight_learned=learned.tolist(), airlight_true=true.tolist(),
                       airlight_error=(learned - true).tolist(), airlight_bias=float((learned - true).mean()))
        else:
            out.update(airlight_learned=None, airlight_true=None, airlight_error=None, airlight_bias=None)
        bias = self.err / n
        mse = float(self.err2.sum() / (3 * n))
        # mean((e - mean e)^2) = mean(e^2) - (mean e)^2, per channel.
        mse_after = max(float((self.err2 / n - bias * bias).mean()), 0.0)
        psnr, after = psnr_of(mse), psnr_of(mse_after)
        out.update(clean_bias=bias.tolist(), mse=mse, mse_share=float(self.err2.sum()) / total_err2 if total_err2
                   else None, psnr=psnr, psnr_offset_removed=after,
                   veil_gain_db=after - psnr if math.isfinite(after) and math.isfinite(psnr) else None)
        return out


def psnr_of(mse: float) -> float:
    """PSNR in dB of a mean squared error, for images in [0, 1] (inf for no error)."""
    return 10.0 * math.log10(1.0 / mse) if mse > 0 else math.inf


# --- the ground truth ------------------------------------------------------------------------
@dataclass
class Truth:
    """One training view's ground truth at the size the run trained it: ``clean`` J [H, W, 3], ``t`` [H, W],
    ``airlight`` A [3], ``distance`` (ray distance, [H, W], inf on sky) and ``sky`` (bool [H, W])."""

    clean: np.ndarray
    t: np.ndarray
    airlight: np.ndarray
    distance: np.ndarray
    sky: np.ndarray


def setting_folder(scene_spec: str, run: Path) -> tuple[Path, dict]:
    """The setting folder a run was trained on and its ``manifest.json``, checked to hold haze layers.

    Raises NimbusError for a built-in scene, a folder ``nimbus-synth degrade`` did not write, or a
    setting without haze (no ``transmission`` / ``airlight`` to compare with).
    """
    from nimbus.train.run_folder import BUILTIN_PREFIX, scene_input_folder
    from weather_synth.dataset import MANIFEST, read_setting_manifest

    how = ("decompose needs a run trained on a setting folder of `nimbus-synth degrade` (or `nimbus-bench run`), "
           "which keeps the true layers")
    if scene_spec.startswith(BUILTIN_PREFIX):
        raise NimbusError(f"run {run} was trained on the built-in scene {scene_spec}, which has no ground-truth "
                          f"layers; {how}")
    folder = scene_input_folder(scene_spec)
    manifest_path = folder / MANIFEST
    if not (folder / "layers").is_dir() or not manifest_path.is_file():
        raise NimbusError(f"the scene of run {run}, {folder}, has no layers/ and {MANIFEST} (it was not "
                          f"synthesised); {how}")
    return folder, read_setting_manifest(folder)


def fit(a: np.ndarray, height: int, width: int) -> np.ndarray:
    """``a`` ([H, W] or [H, W, C]) shrunk to ``height`` x ``width`` by area averaging (the trainer's
    ``train_downscale``); unchanged at that size already."""
    if a.shape[:2] == (height, width):
        return a
    import cv2

    return cv2.resize(a.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)


def read_truth(folder: Path, record: dict, view, height: int, width: int) -> Truth:
    """The ground truth of the view ``record`` (its manifest entry) describes; ``view`` is the setting
    folder's view of that name (world camera, depth and sky files) and ``height`` x ``width`` the size
    the run trained it at."""
    from nimbus.data.images import read_image
    from nimbus.utils.fs import confined_path
    from weather_synth.archive import read_layers

    name = record["name"]
    layers = read_layers(confined_path(folder, record["layers"], "layer archive"))
    missing = [k for k in ("transmission", "airlight") if k not in layers]
    if missing:
        raise NimbusError(f"{folder.name}/{record['layers']} holds no {' or '.join(missing)} (layers: "
                          f"{', '.join(sorted(layers)) or 'none'}): setting {folder.name} has no haze to compare a "
                          "learned medium with; decompose a run of a setting with haze (H, H+R, H+S, H+R+S)")
    depth = layers.get("depth")
    if depth is None:
        depth = view.load_depth()
    if depth is None:
        raise NimbusError(f"view {name} of {folder} has no depth map (depths/ nor a depth layer): the depth bands "
                          "need the depth the haze was made from")
    sky = view.load_sky()
    sky = ~np.isfinite(depth) if sky is None else (sky | ~np.isfinite(depth))
    distance = np.where(sky, np.inf, view.camera.ray_distance_from_z(np.where(sky, 0.0, depth)))
    clean = read_image(confined_path(folder, record["clean"], "clean image"))
    if height != clean.shape[0] or width != clean.shape[1]:
        surface = fit((~sky).astype(np.float32), height, width)
        distance = np.where(surface >= 0.5, fit(np.where(sky, 0.0, distance), height, width)
                            / np.maximum(surface, 1e-6), np.inf)
        sky = surface < 0.5
    return Truth(fit(clean, height, width), fit(layers["transmission"], height, width),
                 np.asarray(layers["airlight"], np.float64).reshape(3), distance, sky)


# --- the learned layers -------------------------------------------------------------------------
def check_medium(runner) -> None:
    """Refuse a run whose model has no medium (3DGS and its baselines, NimbusGS without CSM)."""
    method = runner.method
    if getattr(method, "medium", None) is None:
        what = (f"its NimbusGS components are {', '.join(method.components) or 'none'}, without CSM"
                if hasattr(method, "components") else "the method models no medium")
        raise NimbusError(f"run {runner.out} ({runner.method_name}) learned no transmission or airlight ({what}); "
                          f"decompose takes runs of a method that models a medium: {MEDIUM_METHODS}")


def learned_layers(method, vi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Training view ``vi``'s clean render ``I_hat`` [H, W, 3] (clipped to [0, 1]), transmission ``T`` [H, W, C]
    and scattered light ``P`` [H, W, 3], float64 (see the module docstring for each method's)."""
    import torch

    with torch.no_grad():
        out = method.render(method.train_views[vi].camera, view_index=vi)
    key = next((k for k in SCATTERED_KEYS if k in out), None)
    if key is None or "transmission" not in out:
        raise NimbusError(f"{type(method).__name__}.render(..., view_index=...) returns no transmission and "
                          f"scattered light ({' or '.join(SCATTERED_KEYS)}); decompose cannot read its medium")

    def arr(x):
        return x.detach().double().cpu().numpy()

    return np.clip(arr(out["rgb"]), 0.0, 1.0), arr(out["transmission"]), arr(out[key])


# --- the check --------------------------------------------------------------------------------------
def band_edges(distances: list[np.ndarray]) -> list[float]:
    """``[lo, lo + w, lo + 2 w, hi]``: the thirds of the surface ray distances' range (finite values of
    ``distances``); NimbusError when no view has a surface pixel."""
    finite = [d[np.isfinite(d)] for d in distances]
    finite = [d for d in finite if d.size]
    if not finite:
        raise NimbusError("no training view has a surface pixel (every pixel is sky): there is no depth range to "
                          "cut into bands")
    lo, hi = min(float(d.min()) for d in finite), max(float(d.max()) for d in finite)
    w = (hi - lo) / 3.0
    return [lo, lo + w, lo + 2.0 * w, hi]


def band_masks(truth: Truth, edges: list[float], valid: np.ndarray | None) -> dict[str, np.ndarray]:
    """Each band's pixels (bool [H, W]) of one view; ``valid`` its validity mask (None: every pixel)."""
    keep = np.ones_like(truth.sky) if valid is None else valid
    d = truth.distance
    surface = ~truth.sky & keep
    return {"near": surface & (d < edges[1]), "middle": surface & (d >= edges[1]) & (d < edges[2]),
            "far": surface & (d >= edges[2]), "sky": truth.sky & keep}


def decompose_run(run: str | os.PathLike, device=None) -> dict:
    """The decomposition record of the run folder ``run`` (module docstring), JSON-able.

    Raises
    ------
    NimbusError
        ``run`` is not a finished run folder, its scene has no ground-truth haze layers, or its method
        models no medium.
    """
    from nimbus.data.io import load_scene
    from nimbus.train.run_folder import read_run_config
    from nimbus.train.runner import Runner

    run = Path(run)
    if not run.is_dir():
        raise NimbusError(f"run folder {run} does not exist; give the run folder of a nimbus-train or "
                          "nimbus-bench run cell (bench_runs/runs/CELL)")
    if not (run / "config.json").is_file():
        raise NimbusError(f"{run} is not a run folder of nimbus-train (it has no config.json)")
    saved = read_run_config(run)
    folder, manifest = setting_folder(saved["scene"], run)
    runner = Runner.open(run, progress=False, device=device)
    check_medium(runner)
    method = runner.method
    scene = load_scene(folder)
    by_name = {v.name: v for v in scene.views}
    records = {r.get("name"): r for r in manifest.get("views", []) if isinstance(r, dict)}
    truths = []
    for view in method.train_views:
        if view.name not in records or view.name not in by_name:
            raise NimbusError(f"training view {view.name} of run {run} is not in {folder}'s manifest; the run was "
                              "trained on another version of the scene (synthesise it again and retrain)")
        truths.append(read_truth(folder, records[view.name], by_name[view.name], view.camera.height,
                                 view.camera.width))
    edges = band_edges([t.distance for t in truths])
    sums = {b: BandSums() for b in BANDS}
    for vi, truth in enumerate(truths):
        clean, T, P = learned_layers(method, vi)
        mask = method.train_masks[vi]
        valid = None if mask is None else mask.bool().cpu().numpy().reshape(truth.sky.shape)
        for band, sel in band_masks(truth, edges, valid).items():
            sums[band].add(sel, T, truth.t, P, truth.airlight, clean, truth.clean)
    total = BandSums()
    for s in sums.values():
        total += s
    err2 = float(total.err2.sum())
    bands = {b: s.record(total.pixels, err2) for b, s in {**sums, ALL: total}.items()}
    h, w = method.train_views[0].camera.height, method.train_views[0].camera.width
    return {"format": FORMAT, "run": str(run), "method": runner.method_name, "iteration": runner.iteration,
            "scene": str(folder), "setting": manifest.get("setting", folder.name),
            "protocol": manifest.get("protocol"), "views": len(truths), "size": [w, h],
            "depth": {"measure": "ray distance (scene units)", "edges": edges}, "bands": bands}
