"""One benchmark cell: what it is, the data it trains on, and running it (train, score, record).

A benchmark root holds::

    ROOT/scenes/<scene>-<size>/           the clean built-in scene (rendered once)
    ROOT/data/<scene>-<size>/<SETTING>/   its degraded copies (``nimbus-synth degrade`` layout,
                                          protocol :data:`SYNTH_PROTOCOL`, fixed seed :data:`SYNTH_SEED`)
    ROOT/data/<scene>-<size>@<PROTOCOL>/<SETTING>/
                                          the same in another protocol family (``--weathers H@physical``)
    ROOT/runs/<cell-id>/                  one trainer run directory per cell
    ROOT/results.jsonl                    one record per finished cell (:mod:`benchmark.store`)

Each cell trains its method on the degraded images and is scored with
:mod:`benchmark.metrics` against the *clean* test views (``clean/``): the trainer's own
PSNR compares with the degraded inputs, which is not the benchmark's question.  A weather cell's
record also holds the degraded input's own score (``input_psnr`` / ``input_ssim`` / ``input_lpips``,
:func:`score_input`): its degraded test views against the same clean ones, scored alike, which is
what the reconstruction has to beat.  A cell
trains into ``runs/<cell-id>.partial`` and is renamed into place before it is scored, so a
killed run leaves no half-written run passing for a finished one.  A rerun continues an
interrupted cell from the last checkpoint in its ``.partial`` folder when that folder is this
very cell's (same method, seed, data and config; :func:`resumable_partial`) and the
checkpoint was not cut in the middle of a step; anything else it leaves is removed and the
cell trains from the start.  A resumed cell's record says so (``resumed_from_iteration``); its
training time includes the part before the interruption (the checkpoint carries it).

The clean ceiling: a cell whose setting is :data:`CEILING` (``clean``) trains 3DGS
(:data:`CEILING_METHOD`) on the clean scene folder itself, ``scenes/<scene>-<size>/``: the same
views, split, preset and seed as the weather cells, without the weather, scored against the same
clean test views.  The tables measure each method's loss to the weather against it
(:mod:`benchmark.tables.ceiling`).  It is an ordinary cell otherwise (one id, one run folder, one
record, resumed alike); ``clean`` is no weather token (:mod:`weather_synth.settings`), so its ids
never collide with a weather cell's.

:func:`run_cell` is the one way a cell runs, whoever asks (:mod:`benchmark.grid` for
``nimbus-bench run`` and ``tradeoff``).  The stability report trains on inputs of its own
making, so it uses the steps below it: :func:`train_method` (the grid's and the
stability report's call into the Runner), :func:`score_run`, and the questions it asks a trained model
(:func:`model_parameters`, :func:`medium_composition`).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import shutil
import socket
import time
import traceback
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Iterable, Sequence

from benchmark.store import ResultsStore
from nimbus.errors import NimbusError
from weather_synth.settings import DEFAULT_PROTOCOL, FAMILY_SEPARATOR, parse_family_setting, parse_setting

#: Seed of the built-in scenes' rendering and of the weather synthesis: fixed, so every
#: method and every training seed sees the same degraded images.
SCENE_SEED = 0
SYNTH_SEED = 0
#: The default family's synthesis protocol (the paper's data); other families are named ``SETTING@PROTOCOL``.
SYNTH_PROTOCOL = DEFAULT_PROTOCOL
#: The setting of a clean-ceiling cell: its data folder is the clean scene (module docstring).
CEILING = "clean"
#: The method the clean ceiling trains (plain 3DGS: the weather's cost to the method every other one builds on).
CEILING_METHOD = "3dgs"
DEFAULT_PRESET = "tiny"
DEFAULT_SIZE = "tiny"
PARTIAL_SUFFIX = ".partial"
CELL_FORMAT = "nimbus-bench-cell/1"
#: Status of a record between :func:`train_cell` and :func:`score_cell` (never stored).
TRAINED = "trained"
#: Parameters per Gaussian besides its SH colour: mean 3 + quaternion 4 + log-scale 3 + opacity 1.
GEOMETRY_PARAMS = 11
#: Record fields of the degraded input's own score (:func:`score_input`), by metric; weather cells only.
INPUT_FIELDS = {"psnr": "input_psnr", "ssim": "input_ssim", "lpips": "input_lpips"}


# --- cells -------------------------------------------------------------------------------
@dataclass(frozen=True)
class Cell:
    """One benchmark cell: a method trained on one degraded scene with one preset and seed.

    Attributes
    ----------
    scene : str
        Built-in scene name (``garden``, ``street``, ``tabletop``), or the folder name of a scene read from a
        folder (:mod:`benchmark.scene_sources`).
    weather : str
        Weather setting name (``H``, ``R+S``, ...), ``@PROTOCOL`` for a setting of another synthesis
        protocol's family (``H@physical``; :func:`weather_synth.settings.parse_family_setting`), or
        :data:`CEILING` for a clean-ceiling cell (trained on the clean scene).
    method : str
        Registered method name (:mod:`nimbus.methods.registry`).
    preset : str
        Trainer preset (``tiny``, ``fast``, ``paper``).
    seed : int
        Training seed (the data's seeds are fixed).
    size : str
        Built-in scene size (``tiny``, ``compact``, ``small``, ``standard``); ``images`` / ``images_<N>`` (the image folder read)
        for a scene read from a folder.
    overrides : tuple of (key, value)
        ``--set`` config overrides, sorted.
    """

    scene: str
    weather: str
    method: str
    preset: str = DEFAULT_PRESET
    seed: int = 0
    size: str = DEFAULT_SIZE
    overrides: tuple[tuple[str, str], ...] = ()

    @property
    def cell_id(self) -> str:
        """Stable, file-name-safe id, e.g. ``garden-tiny_H+R_3dgs_tiny_s0`` (+ a hash of any overrides)."""
        cid = f"{self.data_name}_{self.weather}_{self.method}_{self.preset}_s{self.seed}"
        if self.overrides:
            cid += "_" + hashlib.sha256(json.dumps(self.overrides).encode()).hexdigest()[:8]
        return cid

    @property
    def data_name(self) -> str:
        """Name of its data folders (:func:`benchmark.store.data_name_of`): ``garden-tiny``, or a folder's name."""
        from benchmark.store import data_name_of

        return data_name_of(self.scene, self.size)

    @property
    def is_ceiling(self) -> bool:
        """Whether this is a clean-ceiling cell (trained on the clean scene, not a weather setting)."""
        return self.weather == CEILING

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "overrides": dict(self.overrides)}

    @classmethod
    def from_dict(cls, d: dict) -> "Cell":
        return cls(d["scene"], d["weather"], d["method"], d["preset"], int(d["seed"]), d["size"],
                   tuple(sorted(d.get("overrides", {}).items())))


def make_config(method, preset: str, overrides: dict[str, str]):
    """The method's preset with ``--set`` overrides applied (:mod:`nimbus.config_set`)."""
    from nimbus.config_set import apply_overrides

    return apply_overrides(method.preset(preset), overrides)


@dataclass(frozen=True)
class CellOptions:
    """How cells are scored and run (the same for every cell of a grid).

    Attributes
    ----------
    ssim_protocol : str
        :data:`nimbus.metrics.SSIM_PROTOCOLS` name (``3dgs``: the paper's).
    lpips_net : str or None
        ``vgg`` (the paper's), ``alex``, or None to skip LPIPS.
    threads : int or None
        torch CPU threads in the worker (None: leave torch's default).
    device : str or None
        torch device for training (None: CUDA when available, else CPU).
    eval_protocol : str
        :data:`benchmark.metrics.EVAL_PROTOCOLS` name: ``default`` (8-bit round trip) or ``paper``
        (float renders, saved as ``renders_float/<split>/<stem>.npy`` in the run folder).
    """

    ssim_protocol: str = "3dgs"
    lpips_net: str | None = "vgg"
    threads: int | None = None
    device: str | None = None
    eval_protocol: str = "default"

    @property
    def quantize(self) -> bool:
        from benchmark.metrics import get_eval_protocol

        return get_eval_protocol(self.eval_protocol).quantize


# --- data ----------------------------------------------------------------------------------
def scene_dir(root: Path, cell: Cell) -> Path:
    return Path(root) / "scenes" / cell.data_name


def family_dir(root: Path, data_name: str, protocol: str) -> Path:
    """The folder of a scene's degraded settings in one protocol family (the default family's: ``data/<scene>``)."""
    return Path(root) / "data" / (data_name if protocol == SYNTH_PROTOCOL else
                                  f"{data_name}{FAMILY_SEPARATOR}{protocol}")


def data_dir(root: Path, cell: Cell) -> Path:
    """The folder a cell trains on: its degraded setting folder, or the clean scene for a clean-ceiling cell."""
    if cell.is_ceiling:
        return scene_dir(root, cell)
    family = parse_family_setting(cell.weather)
    return family_dir(root, cell.data_name, family.protocol) / family.setting.name


def data_manifest(data: Path) -> Path:
    """The file that says a data folder is complete: its ``manifest.json``, or for a setting copied from a user's
    dataset tree its :data:`~benchmark.scene_sources.LINKED` file (the record's ``input_sha256`` is its hash)."""
    from benchmark.scene_sources import LINKED
    from weather_synth.dataset import MANIFEST

    data = Path(data)
    return data / LINKED if (data / LINKED).is_file() else data / MANIFEST


def run_dir(root: Path, cell: Cell) -> Path:
    return Path(root) / "runs" / cell.cell_id


def partial_dir(root: Path, cell: Cell) -> Path:
    """Where a cell trains before its run folder is renamed into place (:func:`run_dir`)."""
    return run_dir(root, cell).with_name(cell.cell_id + PARTIAL_SUFFIX)


def write_clean_scene(scene: str, size: str, out: Path, progress: bool = False) -> bool:
    """Render a built-in scene into ``out`` (seed :data:`SCENE_SEED`) unless it is there; whether it rendered."""
    from nimbus.data.builtin import write_builtin

    if (Path(out) / "manifest.json").is_file():
        return False
    write_builtin(scene, out, size, seed=SCENE_SEED, overwrite=True, progress=progress)
    return True


def synthesize(clean: Path, out: Path, settings: Sequence[str], config=None, *, progress: bool, source: str) -> None:
    """Degrade the scene in ``clean`` into one ``nimbus-synth degrade`` setting folder per setting under ``out``.

    ``settings`` are plain setting names (no ``@``); ``config`` is a :mod:`weather_synth.config`
    synthesis config (default: the benchmark's, :data:`SYNTH_PROTOCOL` with seed :data:`SYNTH_SEED`).

    Raises
    ------
    NimbusError
        A synthesis parameter is out of range (the synthesizer's own message).
    """
    from nimbus.data.io import load_scene
    from weather_synth.config import protocol_config
    from weather_synth.dataset import degrade_scene

    degrade_scene(load_scene(clean), out, [parse_setting(w) for w in settings],
                  protocol_config(SYNTH_PROTOCOL, SYNTH_SEED) if config is None else config, overwrite=True,
                  progress=progress, source=source)


def prepare_data(root: str | os.PathLike, cells: Iterable[Cell], progress: bool = True,
                 log: Callable[[str], None] | None = None) -> None:
    """Render the clean scenes and synthesise the degraded settings the cells need and the root lacks.

    A clean-ceiling cell needs the clean scene only.  A scene the root records a source of
    (``ROOT/sources/``: a scene folder, photo folder or dataset tree) is prepared from it
    (:func:`benchmark.scene_sources.prepare_source`).

    Both steps write atomically (a folder appears only when complete) with fixed seeds, so a
    run interrupted here resumes by simply doing what is still missing.  Each scene's data is
    prepared under its data lock: a second run waits for the first, then finds the data
    there, instead of replacing folders the first one's cells are reading.
    """
    from benchmark.scene_sources import BUILTIN, CAPTURE_DEPTH, TREE, load_source, prepare_source
    from weather_synth.config import protocol_config
    from weather_synth.dataset import MANIFEST

    root = Path(root)
    need: dict[Cell, dict[str, list[str]]] = {}  # scene -> protocol family -> setting names
    for c in cells:
        key = Cell(c.scene, "", "", size=c.size)
        families = need.setdefault(key, {})
        if c.is_ceiling:
            continue
        family = parse_family_setting(c.weather)
        names = families.setdefault(family.protocol, [])
        if family.setting.name not in names:
            names.append(family.setting.name)
    store = ResultsStore(root)
    for key, families in need.items():
        lock = store.data_lock(key.data_name)
        if not lock.acquire():
            holder = lock.holder()
            if log:
                log(f"waiting for another run ({holder.describe() if holder else 'another process'}) preparing "
                    f"the data of {key.data_name}")
            lock.acquire(wait=True)
        try:
            clean = scene_dir(root, key)
            source = load_source(root, key.data_name)
            builtin = source is None or source.kind == BUILTIN
            if not builtin:
                prepare_source(root, source, families.get(SYNTH_PROTOCOL, []), clean,
                               family_dir(root, key.data_name, SYNTH_PROTOCOL), log)
                if source.kind == TREE:
                    continue
            else:
                if log and not (clean / "manifest.json").is_file():
                    log(f"rendering built-in scene {key.scene} ({key.size}) -> {clean}")
                write_clean_scene(key.scene, key.size, clean, progress=progress)
            for protocol, weathers in families.items():
                out = family_dir(root, key.data_name, protocol)
                missing = [w for w in weathers if not (out / w / MANIFEST).is_file()]
                if missing:
                    config = protocol_config(protocol, SYNTH_SEED)
                    if not builtin:  # a capture: its own depth maps if it has them, else a quick fit
                        config = dataclasses.replace(config, depth=dataclasses.replace(config.depth,
                                                                                       source=CAPTURE_DEPTH))
                    if log:
                        family = "" if protocol == SYNTH_PROTOCOL else f" ({protocol} protocol)"
                        log(f"synthesising {', '.join(missing)}{family} for {key.data_name} -> {out}")
                    synthesize(clean, out, missing, config, progress=progress,
                               source=f"builtin:{key.scene}:{key.size}" if builtin else source.path)
        finally:
            lock.release()


def clear_run_dirs(root: Path, cell: Cell) -> tuple[Path, Path]:
    """Remove what an interrupted or failed earlier attempt left of a cell; its final and partial run folders.

    Only the holder of the cell's lock may call this (:func:`benchmark.grid.run_grid` holds it for
    every cell it runs): another run's cell in flight is never removed.
    """
    final, partial = run_dir(root, cell), partial_dir(root, cell)
    for leftover in (partial, final):
        if leftover.exists():
            shutil.rmtree(leftover)
    return final, partial


def resumable_partial(partial: Path, cell: Cell, config, data: Path, device: str | None = None):
    """A :class:`~nimbus.train.runner.Runner` continuing the interrupted attempt in ``partial``, or None.

    Only a folder written for this very cell qualifies: its ``config.json`` names the cell's
    method and seed, the data folder ``data`` and exactly ``config``; its checkpoint loads and
    was not saved in the middle of a step (Ctrl-C inside a step: the resumed run could differ
    from an uninterrupted one).  A periodic checkpoint (every ``checkpoint_interval`` steps) is
    what a killed process leaves.  ``device`` is the torch device to continue on (None: the default).
    The caller holds the cell's lock.
    """
    import torch

    from nimbus.train.checkpoint import CHECKPOINT
    from nimbus.train.run_folder import config_record, read_run_config
    from nimbus.train.runner import Runner

    if not (partial / CHECKPOINT).is_file():
        return None
    try:
        saved = read_run_config(partial)
    except NimbusError:
        return None
    same = (saved["method"] == cell.method and saved["seed"] == cell.seed and not saved["scene_load_args"]
            and saved["scene"] == str(data.resolve())
            and json.dumps(saved["config"], sort_keys=True) == json.dumps(config_record(config), sort_keys=True))
    if not same:
        return None
    try:
        runner = Runner.resume(partial, progress=False, device=torch.device(device) if device else None)
    except NimbusError:
        return None
    return None if runner.resumed_mid_step else runner


# --- training and scoring ------------------------------------------------------------------------
def train_method(method_name: str, scene, config, out_dir: Path, *, seed: int, scene_path: str, progress: bool,
                 device: str | None = None,
                 model_ready: Callable[[object], None] | None = None, resume_hint: bool = True) -> tuple[dict, object]:
    """Train a registered method on a scene into the run folder ``out_dir``.

    The grid's and the stability report's one call into the Runner: every cell, sweep point and
    stability run goes through here (the scripts under tools/ build their Runners themselves).

    Parameters
    ----------
    method_name : str
        Registered method (:func:`nimbus.methods.registry.get_method`).
    scene : nimbus.data.Scene
    config
        The method's config (:func:`make_config`).
    out_dir : path
        Run folder the trainer writes (renders, log, ``results.json``).
    seed : int
        Training seed.
    scene_path : str
        Where the scene was read from, as the run folder records it.
    progress : bool
        Progress bar on stderr.
    device : str, optional
        torch device (None: CUDA when available, else CPU).
    model_ready : callable(model), optional
        Called with the model once it is built, before it trains: a caller that inspects
        the model after a failed training gets it this way.
    resume_hint : bool
        On an interrupt, say how to continue with ``nimbus-train --resume`` (False: the caller resumes the
        folder itself, as the grid does).

    Returns
    -------
    (dict, object)
        The trainer's results (``results.json``) and the trained model.
    """
    import torch

    from nimbus.train.runner import Runner

    runner = Runner(method_name, scene, config, out_dir, seed=seed, scene_path=scene_path, progress=progress,
                    device=torch.device(device) if device else None)
    runner.resume_hint = resume_hint
    if model_ready is not None:
        model_ready(runner)
    return runner.run(), runner


def model_parameters(model) -> list:
    """Every tensor the model optimises (Gaussians and, for NimbusGS, its medium); ``model`` is a Runner."""
    return [p for g in model.method.param_groups() for p in g["params"]]


def medium_composition(model) -> dict:
    """The extra layers (name -> tensor) of the model's render of its first training view.

    A method that models a medium (NimbusGS and its variants) returns them from
    ``render(camera, view_index=...)`` (``transmission``, ``airlight``, ``residual``, ``degraded``);
    for any other method this is empty.  ``model`` is a :class:`nimbus.train.runner.Runner`.
    """
    m = model.method
    render = m.render(m.train_views[0].camera, view_index=0)
    return {k: v for k, v in render.items() if k not in ("rgb", "depth", "alpha", "meta")}


@functools.lru_cache(maxsize=None)
def _loaded_lpips(net: str, device: str | None):
    from nimbus.metrics import LPIPS

    # No ground-truth feature cache: it would grow over a run's cells, and each cell's
    # LPIPS is computed from the same batches as by a network loaded for it alone.
    return LPIPS(net, device=device, gt_cache_mb=0)


def scoring_lpips(options: CellOptions):
    """The LPIPS the cells of ``options`` are scored with, loaded once per process; None without LPIPS.

    Where its weights are not set up this is the network's name: the score then notes LPIPS as
    missing (:class:`benchmark.metrics.Scorer`).
    """
    from nimbus.metrics import WeightsMissing

    if options.lpips_net is None:
        return None
    try:
        return _loaded_lpips(options.lpips_net, options.device)
    except WeightsMissing:
        return options.lpips_net


def runs_on_cuda(options: CellOptions) -> bool:
    """Whether the cells of ``options`` train on CUDA (its ``device``, else CUDA when torch sees a GPU)."""
    import torch

    from nimbus.methods.base import default_device

    return (torch.device(options.device) if options.device else default_device()).type == "cuda"


def warm_up(options: CellOptions, reverse: bool = False) -> None:
    """Load now what every cell would load on first use: for a process about to train many cells.

    torch with the cells' threads, the default methods' modules and what the cells' device renders
    with: on the CPU the compiled kernels, on CUDA gsplat's extension (when gsplat is installed) and not the CPU kernels, which
    a CUDA cell never calls.  No cell's training time then includes them, and every cell's peak
    memory is measured over the same loaded baseline.  Best effort: what fails here fails again in
    the cell, which records why.

    ``reverse`` loads the CPU kernels' libraries in the opposite order: two workers that start together
    then build different libraries at once instead of one waiting on the other's build lock (docs/performance.md,
    "Workers and threads").
    """
    import torch

    if options.threads:
        torch.set_num_threads(int(options.threads))
    try:
        from nimbus.methods.registry import get_method

        for name in ("3dgs", "nimbus", "restore-3dgs"):
            get_method(name).load()
        if runs_on_cuda(options):
            from nimbus.render.backends import gsplat

            gsplat.package_available()
            return
        from nimbus.kernels import march, raster, train_step

        loads = [raster.available, march.EXTENSION.available, train_step.EXTENSION.available]
        for load in loads[::-1] if reverse else loads:
            load(warn=False)
    except Exception:  # noqa: BLE001 - the cell meets it again and records it
        pass


#: Folder of a run's float renders (the paper protocol's predictions), beside ``renders/``.
FLOAT_RENDERS = "renders_float"


def save_float_renders(model, out: Path, split: str) -> None:
    """Render ``split``'s views of a trained Runner as float32 ``out/renders_float/<split>/<stem>.npy``.

    The views :meth:`nimbus.train.runner.Runner.evaluate` rendered as PNGs, without their 8-bit
    rounding: what the paper protocol scores.
    """
    import numpy as np
    import torch

    views = model.scene.test_views if split == "test" else model.scene.train_views
    folder = Path(out) / FLOAT_RENDERS / split
    folder.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        for view in views:
            rgb = model.method.render(view.camera)["rgb"].clamp(0, 1).float().cpu().numpy()
            np.save(folder / f"{view.stem}.npy", rgb, allow_pickle=False)


def score_run(run: Path, data: Path, results: dict, *, ssim_protocol: str, lpips_net, device: str | None,
              quantize: bool = True) -> dict:
    """Score a trained run's renders of its evaluation split against the ground truth of ``data``.

    ``data`` is a setting folder (``clean/`` holds the ground truth); ``lpips_net`` is a network
    name, a loaded :class:`nimbus.metrics.LPIPS` or None.  ``quantize`` False scores the run's
    float renders (:func:`save_float_renders`) without 8-bit rounding.  A missing LPIPS is left to the
    score's notes rather than warned about.  Returns :func:`benchmark.score.score_renders`'s dict.
    """
    from benchmark.score import score_renders

    split = results.get("eval_split", "test")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return score_renders(Path(run) / ("renders" if quantize else FLOAT_RENDERS) / split, data, split=split,
                             ssim_protocol=ssim_protocol, lpips_net=lpips_net, device=device, quantize=quantize)


def score_input(data: Path, split: str, *, ssim_protocol: str, lpips_net, device: str | None) -> dict:
    """Score a setting's degraded ``split`` views themselves against its clean ones, as a cell's renders are scored.

    What a reconstruction has to beat: the images the weather left (``data/images/``, what the synthesiser wrote)
    scored by :func:`benchmark.score.score_renders` exactly as :func:`score_run` scores a run's renders: the
    same ground truth (``clean/``), views, validity masks, SSIM protocol and LPIPS network.  The inputs are 8-bit
    image files, which the 8-bit round trip leaves as they are, so this one score serves both evaluation protocols
    (a 16-bit input of a dataset tree is scored through the round trip).  Returns ``score_renders``'s dict.
    """
    from benchmark.score import score_renders
    from weather_synth.dataset import IMAGE_DIR

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return score_renders(Path(data) / IMAGE_DIR, data, split=split, ssim_protocol=ssim_protocol,
                             lpips_net=lpips_net, device=device, quantize=True)


# --- one cell ----------------------------------------------------------------------------------
def utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def config_hash(config) -> str:
    """sha256 of the config as canonical JSON (sorted keys)."""
    blob = json.dumps(dataclasses.asdict(config), sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()


def base_record(cell: Cell) -> dict:
    """The fields every record has, whatever happened to the cell."""
    from benchmark.score import versions

    return {"format": CELL_FORMAT, "cell_id": cell.cell_id, **cell.to_dict(), "versions": versions(),
            "host": socket.gethostname(), "started_at": utc_now()}


def error_record(cell: Cell, message: str, started_at: str | None = None) -> dict:
    """A record for a cell that ended in an error (rerun retries it)."""
    rec = base_record(cell)
    if started_at:
        rec["started_at"] = started_at
    rec.update(status="error", error=message, finished_at=utc_now())
    return rec


def run_cell(cell: dict | Cell, root: str, options: CellOptions | None = None) -> dict:
    """Train, render and score one cell; never raises for a failure of the cell itself.

    Runs in a worker (process or Dask task): it reads the prepared data under ``root`` and
    writes ``root/runs/<cell-id>/``, and returns the record for the parent to store.  It is
    :func:`train_cell` then :func:`score_cell`; the local executor runs the first in its
    worker processes and the second in the parent (:mod:`benchmark.workers`).

    Returns
    -------
    dict
        JSON-ready record: the cell's fields; ``status`` ``"ok"`` or ``"error"`` (with
        ``error``); ``psnr`` (dB) / ``ssim`` / ``lpips`` means against the clean test views
        and ``per_view`` values; ``ssim_protocol``, ``lpips_net``, ``notes``;
        ``psnr_vs_input`` / ``ssim_vs_input`` (the trainer's own score, when it was against the
        degraded views; None when the data has ``clean/``, which the trainer then scores against);
        ``input_psnr`` / ``input_ssim`` / ``input_lpips`` (a weather cell's degraded test views themselves against
        the clean ones, :func:`score_input`: the score without any reconstruction; none for a clean-ceiling cell);
        ``train_time_s``, ``peak_memory_mb`` (of the process that trained; of its last attempt for a cell
        resumed after an interruption, whose record has ``resumed_from_iteration``), ``num_gaussians``,
        ``num_params`` (+ ``num_params_source``), ``render_fps``, ``iterations``;
        ``config``, ``config_hash``; ``versions``; ``input_sha256`` (the degraded dataset's
        manifest; the clean scene's for a clean-ceiling cell), ``output_sha256`` (render name ->
        sha256); ``run_dir`` (relative to root); ``started_at`` / ``finished_at`` (UTC ISO 8601) and ``wall_time_s``.
    """
    options = options or CellOptions()
    return score_cell(train_cell(cell, root, options), root, options)


def train_cell(cell: dict | Cell, root: str, options: CellOptions) -> dict:
    """Train one cell and render its test views: its record without scores (status :data:`TRAINED`), or an error
    record; never raises for a failure of the cell itself."""
    cell = Cell.from_dict(cell) if isinstance(cell, dict) else cell
    return _attempt(base_record(cell), lambda: _train_cell(cell, Path(root), options), TRAINED)


def score_cell(record: dict, root: str, options: CellOptions) -> dict:
    """Score the renders of a :func:`train_cell` record: the finished record (``ok`` or ``error``).

    Any other record (an error) is returned as it is.  Never raises for a failure of the cell itself.
    """
    if record.get("status") != TRAINED:
        return record
    return _attempt(dict(record), lambda: _score_cell(record, Path(root), options), "ok")


def _attempt(rec: dict, step: Callable[[], dict], status: str) -> dict:
    """``rec`` with ``step()``'s fields and ``status``, or with the error it raised; its time added to ``wall_time_s``."""
    t0 = time.perf_counter()
    try:
        rec.update(step())
        rec["status"] = status
    except NimbusError as e:
        rec.update(status="error", error=str(e))
    except Exception as e:  # recorded, not raised: one broken cell must not stop a grid
        tb = traceback.format_exc(limit=-3)
        rec.update(status="error", error=f"{e.__class__.__name__}: {e}", traceback=tb)
    rec["finished_at"] = utc_now()
    rec["wall_time_s"] = round(rec.get("wall_time_s", 0.0) + time.perf_counter() - t0, 3)
    from nimbus.utils.jsonable import jsonable

    return jsonable(rec)


def _train_cell(cell: Cell, root: Path, options: CellOptions) -> dict:
    import torch

    from nimbus.data.io import load_scene
    from nimbus.methods.registry import get_method
    from nimbus.train.run_folder import config_record

    if options.threads:
        torch.set_num_threads(int(options.threads))
    config = make_config(get_method(cell.method), cell.preset, dict(cell.overrides))
    data = data_dir(root, cell)
    if not data_manifest(data).is_file():
        raise NimbusError(f"{data} is missing; the grid runner prepares it before training (is ROOT shared "
                          "with the workers?)")
    final, partial = run_dir(root, cell), partial_dir(root, cell)
    resumed = resumable_partial(partial, cell, config, data, options.device)
    if resumed is not None:
        resumed.resume_hint = False  # the grid resumes its cells: nimbus-bench's own message says how
        resumed_from = resumed.iteration
        if final.exists():  # an earlier finished attempt's folder (--rerun): the resumed one replaces it
            shutil.rmtree(final)
        results, model = resumed.run(), resumed
    else:
        resumed_from = None
        final, partial = clear_run_dirs(root, cell)
        scene = load_scene(data)
        results, model = train_method(cell.method, scene, config, partial, seed=cell.seed,
                                      scene_path=str(data.resolve()), progress=False, device=options.device,
                                      resume_hint=False)
    num_params, source = _param_count(model, results, config)
    if not options.quantize:
        save_float_renders(model, partial, results.get("eval_split", "test"))
    os.replace(partial, final)
    out = {
        # The trainer scores against clean/ when the data has it: then its figures are psnr / ssim, not "vs input".
        **({"psnr_vs_input": None, "ssim_vs_input": None} if results.get("eval_reference") == "clean" else
           {"psnr_vs_input": results.get("psnr"), "ssim_vs_input": results.get("ssim")}),
        "train_time_s": results.get("train_time_s"), "peak_memory_mb": results.get("peak_memory_mb"),
        "threads": results.get("threads"),
        "num_gaussians": results.get("num_gaussians"), "num_params": num_params, "num_params_source": source,
        "render_fps": results.get("render_fps"), "iterations": results.get("iterations"),
        "device": results.get("device"), "rasterizer": results.get("rasterizer"), "config": config_record(config),
        "config_hash": config_hash(config), "config_type": type(config).__name__,
        "run_dir": str(final.relative_to(root)),
    }
    if "components" in results:
        out["components"] = results["components"]
    if resumed_from is not None:
        out["resumed_from_iteration"] = resumed_from
    return out


def _score_cell(record: dict, root: Path, options: CellOptions) -> dict:
    from benchmark.store import record_data_name, record_run_dir
    from nimbus.utils.fs import sha256_file

    record_data_name(record)  # the record's fields name folders: they must stay in the root
    cell = Cell.from_dict(record)
    data = data_dir(root, cell)
    final = record_run_dir(root, record)
    results = json.loads((final / "results.json").read_text())
    lpips = scoring_lpips(options)
    score = score_run(final, data, results, ssim_protocol=options.ssim_protocol, lpips_net=lpips,
                      device=options.device, quantize=options.quantize)
    per_view = [{k: v[k] for k in ("name", "psnr", "ssim", "lpips")} for v in score["per_view"]]
    manifest_sha256 = sha256_file(data_manifest(data))
    return {
        **_input_fields(cell, data, manifest_sha256, results.get("eval_split", "test"), options, lpips),
        "psnr": score["mean"]["psnr"], "ssim": score["mean"]["ssim"], "lpips": score["mean"]["lpips"],
        "per_view": per_view, "ssim_protocol": options.ssim_protocol, "lpips_net": options.lpips_net,
        "protocol": score["protocol"], "eval_protocol": options.eval_protocol, "notes": score["notes"], "setup_command": score.get("setup_command"),
        "ground_truth": score["ground_truth"],
        "input_sha256": manifest_sha256,
        "output_sha256": {v["name"]: v["pred_sha256"] for v in score["per_view"]},
    }


def _input_fields(cell: Cell, data: Path, manifest_sha256: str, split: str, options: CellOptions, lpips) -> dict:
    """:data:`INPUT_FIELDS` of a weather cell's record (:func:`score_input`); none for a clean-ceiling cell, which
    has no degraded input, nor for data without ``clean/`` views to score it against.

    Every method of a setting has the same input: it is scored once per process (:func:`_input_score`)."""
    from benchmark.score import CLEAN_DIR

    if cell.is_ceiling or not (data / CLEAN_DIR).is_dir():
        return {}
    return dict(_input_score(str(data.resolve()), manifest_sha256, split, options.ssim_protocol, lpips,
                             options.device))


@functools.lru_cache(maxsize=256)
def _input_score(data: str, manifest_sha256: str, split: str, ssim_protocol: str, lpips,
                 device: str | None) -> tuple:
    """:data:`INPUT_FIELDS` of the setting folder ``data`` as ``(field, value)`` pairs, computed once per process for
    a given dataset manifest (its sha256, so a folder synthesised again is scored again) and scoring protocol."""
    score = score_input(Path(data), split, ssim_protocol=ssim_protocol, lpips_net=lpips, device=device)
    return tuple((field, score["mean"][k]) for k, field in INPUT_FIELDS.items())


def _param_count(model, results: dict, config) -> tuple[int | None, str]:
    """Optimised parameter count: the trainer's tensors when it exposes them, else Gaussians x per-Gaussian."""
    if isinstance(results.get("num_params"), int):
        return results["num_params"], "trainer"
    try:
        n = sum(int(p.numel()) for p in model_parameters(model))
        return n, "optimiser parameter groups"
    except Exception:
        g = results.get("num_gaussians")
        per = GEOMETRY_PARAMS + 3 * (getattr(config, "sh_degree", 3) + 1) ** 2
        return (None if g is None else int(g) * per), f"num_gaussians x {per}"
