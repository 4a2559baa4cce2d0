"""The benchmark grid: cells (scene, weather, method, preset, seed), data preparation, and executors.

A benchmark root holds::

    ROOT/scenes/<scene>-<size>/           the clean built-in scene (rendered once)
    ROOT/data/<scene>-<size>/<SETTING>/   its degraded copies (``nimbus-synth degrade`` layout,
                                          fixed synthesis seed :data:`SYNTH_SEED`)
    ROOT/runs/<cell-id>/                  one trainer run directory per cell
    ROOT/results.jsonl                    one record per finished cell (:mod:`benchmark.store`)

Each cell trains its method on the degraded images and is scored with
:mod:`benchmark.metrics` against the *clean* test views (``clean/``): the trainer's own
PSNR compares with the degraded inputs, which is not the benchmark's question.

Executors
    :class:`LocalExecutor` runs cells in local processes (``--jobs N``; by default each
    cell gets a fresh process, so its peak-memory figure is its own);
    :class:`DaskExecutor` submits each cell as a task to a Dask distributed cluster (the
    workers must see ``ROOT`` on a shared file system).  Either way only the parent
    process writes the store, as each cell's record comes back.

Resumption
    A cell with an ``ok`` record is skipped (a later error record never hides it; see
    :mod:`benchmark.store`).  A cell trains into ``runs/<cell-id>.partial`` and is renamed
    into place before it is scored, so a killed run leaves no half-written run passing for
    a finished one; a rerun removes leftovers.

Several runs on one root
    The parent holds each cell's lock (:meth:`benchmark.store.ResultsStore.cell_lock`) from
    before the cell's folders are touched until its record is stored, and takes the locks of
    all its cells before it starts: a second run on the same root skips the cells a live run
    holds (reported as running elsewhere, not failed) and so never removes that run's
    folders.  A lock whose process has died is free and taken over.  Data preparation waits
    for another run preparing the same scene (:meth:`~benchmark.store.ResultsStore.data_lock`).
    Not covered: a Dask task still running on a worker after its parent was killed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import socket
import sys
import time
import traceback
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Iterable, Iterator, Protocol, Sequence

from benchmark.store import FileLock, ResultsStore
from nimbus.errors import NimbusError

#: Seed of the built-in scenes' rendering and of the weather synthesis: fixed, so every
#: method and every training seed sees the same degraded images.
SCENE_SEED = 0
SYNTH_SEED = 0
SYNTH_PROTOCOL = "onerestore"
#: Methods of the default benchmark, in table order (those not registered are skipped).
DEFAULT_METHODS = ("nimbus", "3dgs")
DEFAULT_PRESET = "tiny"
DEFAULT_SIZE = "tiny"
PARTIAL_SUFFIX = ".partial"
CELL_FORMAT = "nimbus-bench-cell/1"
#: Parameters per Gaussian besides its SH colour: mean 3 + quaternion 4 + log-scale 3 + opacity 1.
GEOMETRY_PARAMS = 11


# --- cells -------------------------------------------------------------------------------
@dataclass(frozen=True)
class Cell:
    """One benchmark cell: a method trained on one degraded scene with one preset and seed.

    Attributes
    ----------
    scene : str
        Built-in scene name (``garden``, ``street``, ``tabletop``).
    weather : str
        Weather setting name (``H``, ``R+S``, ...; :mod:`weather_synth.settings`).
    method : str
        Registered method name (:mod:`nimbus.train.methods`).
    preset : str
        Trainer preset (``tiny``, ``fast``, ``paper``).
    seed : int
        Training seed (the data's seeds are fixed).
    size : str
        Built-in scene size (``tiny``, ``small``, ``standard``).
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
        return f"{self.scene}-{self.size}"

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "overrides": dict(self.overrides)}

    @classmethod
    def from_dict(cls, d: dict) -> "Cell":
        return cls(d["scene"], d["weather"], d["method"], d["preset"], int(d["seed"]), d["size"],
                   tuple(sorted(d.get("overrides", {}).items())))


def resolve_methods(spec: str | None) -> tuple[list[str], list[str]]:
    """Method names to run and the default ones skipped because they are not registered.

    ``spec`` None (or ``"default"``) is :data:`DEFAULT_METHODS`, keeping the registered ones;
    an explicit comma list must name registered methods only (NimbusError otherwise).
    """
    from nimbus.train.methods import METHODS, get_method

    if spec is None or spec.strip() == "default":
        names = [m for m in DEFAULT_METHODS if m in METHODS]
        return names, [m for m in DEFAULT_METHODS if m not in METHODS]
    names = _split(spec, "--methods")
    for n in names:
        get_method(n)
    return names, []


def _split(spec: str, what: str) -> list[str]:
    out = []
    for item in spec.split(","):
        item = item.strip()
        if item and item not in out:
            out.append(item)
    if not out:
        raise NimbusError(f"{what} is empty; give a comma-separated list")
    return out


def build_cells(scenes: Sequence[str], weathers: Sequence[str], methods: Sequence[str], presets: Sequence[str],
                seeds: Sequence[int], size: str = DEFAULT_SIZE, overrides: dict[str, str] | None = None) -> list[Cell]:
    """Every combination, in table order (scene, weather, method, preset, seed); validated before any work.

    Raises
    ------
    NimbusError
        Unknown scene, size, weather, method or preset, a negative seed, or an override the
        method's config does not have.
    """
    from nimbus.data.builtin import get_scene, get_size
    from nimbus.train.methods import get_method
    from weather_synth.settings import parse_setting

    get_size(size)
    for s in scenes:
        get_scene(s)
    weathers = [parse_setting(w).name for w in weathers]
    for seed in seeds:
        if seed < 0:
            raise NimbusError(f"seeds must be non-negative, got {seed}")
    ov = tuple(sorted((overrides or {}).items()))
    for m in methods:
        for p in presets:
            make_config(get_method(m), p, dict(ov))  # a bad preset or --set fails here, not in a worker
    return [Cell(sc, w, m, p, int(seed), size, ov)
            for sc in scenes for w in weathers for m in methods for p in presets for seed in seeds]


def make_config(method, preset: str, overrides: dict[str, str]):
    """The method's preset with ``--set`` overrides applied (:mod:`nimbus.config_set`)."""
    from nimbus.config_set import apply_overrides

    return apply_overrides(method.preset(preset), overrides)


# --- data ----------------------------------------------------------------------------------
def scene_dir(root: Path, cell: Cell) -> Path:
    return Path(root) / "scenes" / cell.data_name


def data_dir(root: Path, cell: Cell) -> Path:
    """The degraded setting folder a cell trains on."""
    return Path(root) / "data" / cell.data_name / cell.weather


def run_dir(root: Path, cell: Cell) -> Path:
    return Path(root) / "runs" / cell.cell_id


def prepare_data(root: str | os.PathLike, cells: Iterable[Cell], progress: bool = True,
                 log: Callable[[str], None] | None = None) -> None:
    """Render the clean scenes and synthesise the degraded settings the cells need and the root lacks.

    Both steps write atomically (a folder appears only when complete) with fixed seeds, so a
    run interrupted here resumes by simply doing what is still missing.  Each scene's data is
    prepared under its data lock: a second run waits for the first, then finds the data
    there, instead of replacing folders the first one's cells are reading.
    """
    from nimbus.data.builtin import write_builtin
    from nimbus.data.io import load_scene
    from weather_synth.config import protocol_config
    from weather_synth.dataset import MANIFEST, degrade_scene
    from weather_synth.settings import parse_setting

    root = Path(root)
    need: dict[Cell, list[str]] = {}
    for c in cells:
        key = Cell(c.scene, "", "", size=c.size)
        if c.weather not in need.setdefault(key, []):
            need[key].append(c.weather)
    store = ResultsStore(root)
    for key, weathers in need.items():
        lock = store.data_lock(key.data_name)
        if not lock.acquire():
            holder = lock.holder()
            if log:
                log(f"waiting for another run ({holder.describe() if holder else 'another process'}) preparing "
                    f"the data of {key.data_name}")
            lock.acquire(wait=True)
        try:
            clean = scene_dir(root, key)
            if not (clean / "manifest.json").is_file():
                if log:
                    log(f"rendering built-in scene {key.scene} ({key.size}) -> {clean}")
                write_builtin(key.scene, clean, key.size, seed=SCENE_SEED, overwrite=True, progress=progress)
            out = root / "data" / key.data_name
            missing = [w for w in weathers if not (out / w / MANIFEST).is_file()]
            if missing:
                if log:
                    log(f"synthesising {', '.join(missing)} for {key.data_name} -> {out}")
                degrade_scene(load_scene(clean), out, [parse_setting(w) for w in missing],
                              protocol_config(SYNTH_PROTOCOL, SYNTH_SEED), overwrite=True, progress=progress,
                              source=f"builtin:{key.scene}:{key.size}")
        finally:
            lock.release()


# --- one cell ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class CellOptions:
    """How cells are scored and run (the same for every cell of a grid).

    Attributes
    ----------
    ssim_protocol : str
        :data:`benchmark.metrics.SSIM_PROTOCOLS` name (``3dgs``: the paper's).
    lpips_net : str or None
        ``vgg`` (the paper's), ``alex``, or None to skip LPIPS.
    threads : int or None
        torch CPU threads in the worker (None: leave torch's default).
    device : str or None
        torch device for training (None: CUDA when available, else CPU).
    """

    ssim_protocol: str = "3dgs"
    lpips_net: str | None = "vgg"
    threads: int | None = None
    device: str | None = None


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def config_hash(config) -> str:
    """sha256 of the config as canonical JSON (sorted keys)."""
    blob = json.dumps(dataclasses.asdict(config), sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()


def base_record(cell: Cell) -> dict:
    """The fields every record has, whatever happened to the cell."""
    from benchmark.score import versions

    return {"format": CELL_FORMAT, "cell_id": cell.cell_id, **cell.to_dict(), "versions": versions(),
            "host": socket.gethostname(), "started_at": _now()}


def error_record(cell: Cell, message: str, started_at: str | None = None) -> dict:
    """A record for a cell that ended in an error (rerun retries it)."""
    rec = base_record(cell)
    if started_at:
        rec["started_at"] = started_at
    rec.update(status="error", error=message, finished_at=_now())
    return rec


def run_cell(cell: dict | Cell, root: str, options: CellOptions | None = None) -> dict:
    """Train, render and score one cell; never raises for a failure of the cell itself.

    Runs in a worker (process or Dask task): it reads the prepared data under ``root`` and
    writes ``root/runs/<cell-id>/``, and returns the record for the parent to store.

    Returns
    -------
    dict
        JSON-ready record: the cell's fields; ``status`` ``"ok"`` or ``"error"`` (with
        ``error``); ``psnr`` (dB) / ``ssim`` / ``lpips`` means against the clean test views
        and ``per_view`` values; ``ssim_protocol``, ``lpips_net``, ``notes``;
        ``psnr_vs_input`` / ``ssim_vs_input`` (the trainer's, against the degraded views);
        ``train_time_s``, ``peak_memory_mb`` (of the worker process), ``num_gaussians``,
        ``num_params`` (+ ``num_params_source``), ``render_fps``, ``iterations``;
        ``config``, ``config_hash``; ``versions``; ``input_sha256`` (the degraded dataset's
        manifest), ``output_sha256`` (render name -> sha256); ``run_dir`` (relative to
        root); ``started_at`` / ``finished_at`` (UTC ISO 8601) and ``wall_time_s``.
    """
    cell = Cell.from_dict(cell) if isinstance(cell, dict) else cell
    options = options or CellOptions()
    rec = base_record(cell)
    t0 = time.perf_counter()
    try:
        rec.update(_run_cell(cell, Path(root), options))
        rec["status"] = "ok"
    except NimbusError as e:
        rec.update(status="error", error=str(e))
    except Exception as e:  # recorded, not raised: one broken cell must not stop a grid
        tb = traceback.format_exc(limit=-3)
        rec.update(status="error", error=f"{e.__class__.__name__}: {e}", traceback=tb)
    rec["finished_at"] = _now()
    rec["wall_time_s"] = round(time.perf_counter() - t0, 3)
    from nimbus.utils.jsonable import jsonable

    return jsonable(rec)


def _run_cell(cell: Cell, root: Path, options: CellOptions) -> dict:
    import torch

    from benchmark.score import score_renders
    from nimbus.data.io import load_scene
    from nimbus.train.methods import get_method
    from nimbus.utils.fs import sha256_file
    from weather_synth.dataset import MANIFEST

    if options.threads:
        torch.set_num_threads(int(options.threads))
    method = get_method(cell.method)
    config = make_config(method, cell.preset, dict(cell.overrides))
    data = data_dir(root, cell)
    if not (data / MANIFEST).is_file():
        raise NimbusError(f"{data} is missing; the grid runner prepares it before training (is ROOT shared "
                          "with the workers?)")
    final, partial = clear_run_dirs(root, cell)
    scene = load_scene(data)
    trainer = method.trainer()(scene, config, partial, seed=cell.seed, scene_path=str(data.resolve()),
                               progress=False, device=torch.device(options.device) if options.device else None)
    results = trainer.train()
    num_params, source = _param_count(trainer, results, config)
    del trainer
    os.replace(partial, final)
    split_dir = final / "renders" / results.get("eval_split", "test")
    with warnings.catch_warnings():  # a missing LPIPS is recorded in the notes
        warnings.simplefilter("ignore", UserWarning)
        score = score_renders(split_dir, data, split=results.get("eval_split", "test"),
                              ssim_protocol=options.ssim_protocol, lpips_net=options.lpips_net,
                              device=options.device)
    per_view = [{k: v[k] for k in ("name", "psnr", "ssim", "lpips")} for v in score["per_view"]]
    out = {
        "psnr": score["mean"]["psnr"], "ssim": score["mean"]["ssim"], "lpips": score["mean"]["lpips"],
        "per_view": per_view, "ssim_protocol": options.ssim_protocol, "lpips_net": options.lpips_net,
        "protocol": score["protocol"], "notes": score["notes"], "setup_command": score.get("setup_command"),
        "ground_truth": score["ground_truth"],
        "psnr_vs_input": results.get("psnr"), "ssim_vs_input": results.get("ssim"),
        "train_time_s": results.get("train_time_s"), "peak_memory_mb": results.get("peak_memory_mb"),
        "num_gaussians": results.get("num_gaussians"), "num_params": num_params, "num_params_source": source,
        "render_fps": results.get("render_fps"), "iterations": results.get("iterations"),
        "device": results.get("device"), "config": dataclasses.asdict(config), "config_hash": config_hash(config),
        "config_type": type(config).__name__,
        "input_sha256": sha256_file(data / MANIFEST),
        "output_sha256": {v["name"]: v["pred_sha256"] for v in score["per_view"]},
        "run_dir": str(final.relative_to(root)),
    }
    if "components" in results:
        out["components"] = results["components"]
    return out


def clear_run_dirs(root: Path, cell: Cell) -> tuple[Path, Path]:
    """Remove what an interrupted or failed earlier attempt left of a cell; its final and partial run folders.

    Only the holder of the cell's lock may call this (:func:`run_grid` holds it for every cell it
    runs): another run's cell in flight is never removed.
    """
    final = run_dir(root, cell)
    partial = final.with_name(cell.cell_id + PARTIAL_SUFFIX)
    for leftover in (partial, final):
        if leftover.exists():
            shutil.rmtree(leftover)
    return final, partial


def _param_count(trainer, results: dict, config) -> tuple[int | None, str]:
    """Optimised parameter count: the trainer's tensors when it exposes them, else Gaussians x per-Gaussian."""
    if isinstance(results.get("num_params"), int):
        return results["num_params"], "trainer"
    try:
        n = sum(int(p.numel()) for g in trainer.all_param_groups() for p in g["params"])
        return n, "optimiser parameter groups"
    except Exception:
        g = results.get("num_gaussians")
        per = GEOMETRY_PARAMS + 3 * (getattr(config, "sh_degree", 3) + 1) ** 2
        return (None if g is None else int(g) * per), f"num_gaussians x {per}"


# --- executors -----------------------------------------------------------------------------------
class Executor(Protocol):
    """Runs cells and yields their records as they finish (in any order)."""

    def imap(self, cells: Sequence[Cell], root: str, options: CellOptions) -> Iterator[dict]: ...


class InlineExecutor:
    """Runs cells one after the other in this process (debugging; tests)."""

    name = "inline"

    def imap(self, cells: Sequence[Cell], root: str, options: CellOptions) -> Iterator[dict]:
        for c in cells:
            yield run_cell(c, root, options)


class LocalExecutor:
    """Runs cells in local worker processes.

    Parameters
    ----------
    jobs : int
        Cells run at once (default 1).  Each worker gets ``max(1, cores // jobs)`` torch threads.
    fresh_process : bool
        Start a new process for every cell (default): its peak memory is the cell's own
        and nothing leaks between cells, for ~2 s of start-up per cell.
    """

    name = "local"

    def __init__(self, jobs: int = 1, fresh_process: bool = True) -> None:
        if jobs < 1:
            raise NimbusError(f"--jobs must be at least 1, got {jobs}")
        self.jobs = int(jobs)
        self.fresh_process = fresh_process

    def threads(self) -> int:
        return max(1, (os.cpu_count() or 1) // self.jobs)

    def imap(self, cells: Sequence[Cell], root: str, options: CellOptions) -> Iterator[dict]:
        import multiprocessing

        if options.threads is None:
            options = dataclasses.replace(options, threads=self.threads())
        # spawn, not fork: forking a process that has started torch's thread pools can deadlock.
        pool = ProcessPoolExecutor(max_workers=min(self.jobs, max(len(cells), 1)),
                                   mp_context=multiprocessing.get_context("spawn"),
                                   max_tasks_per_child=1 if self.fresh_process else None)
        started = {}
        try:
            futures = {}
            for c in cells:
                futures[pool.submit(run_cell, c.to_dict(), root, options)] = c
                started[c] = _now()
            for fut in as_completed(futures):
                c = futures[fut]
                try:
                    yield fut.result()
                except Exception as e:  # the worker died (killed, out of memory): the cell failed
                    yield error_record(c, f"worker process failed ({e.__class__.__name__}: {e}); "
                                          "out of memory? try fewer --jobs", started[c])
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


class DaskExecutor:
    """Submits each cell as a task to a Dask distributed cluster and yields records as they finish.

    Parameters
    ----------
    scheduler : str or distributed.Client
        Scheduler address (``tcp://host:8786``) or a connected client.  The workers must
        import this package and see ``ROOT`` at the same path (shared file system).
    """

    name = "dask"

    def __init__(self, scheduler) -> None:
        if scheduler is None or (isinstance(scheduler, str) and not scheduler.strip()):
            raise NimbusError("--executor dask needs --scheduler ADDRESS (e.g. tcp://10.0.0.5:8786)")
        self.scheduler = scheduler

    def _client(self):
        try:
            from distributed import Client
        except ImportError:
            raise NimbusError("--executor dask needs the 'distributed' package (pip install distributed)") from None
        if not isinstance(self.scheduler, str):
            return self.scheduler, False
        try:
            return Client(self.scheduler, timeout="20s"), True
        except (OSError, TimeoutError) as e:
            raise NimbusError(f"cannot reach the Dask scheduler at {self.scheduler} ({e}); start it with "
                              "`dask scheduler` and workers with `dask worker ADDRESS`") from None

    def imap(self, cells: Sequence[Cell], root: str, options: CellOptions) -> Iterator[dict]:
        from distributed import as_completed as dask_completed

        client, own = self._client()
        started = {}
        try:
            futures = {}
            for c in cells:
                fut = client.submit(run_cell, c.to_dict(), str(Path(root).resolve()), options,
                                    key=f"nimbus-cell-{c.cell_id}-{os.getpid()}-{time.time_ns()}", pure=False)
                futures[fut.key] = (fut, c)
                started[c] = _now()
            for fut in dask_completed([f for f, _ in futures.values()]):
                c = futures[fut.key][1]
                try:
                    yield fut.result()
                except Exception as e:  # the task itself failed (worker lost, unpicklable, ...)
                    yield error_record(c, f"Dask task failed ({e.__class__.__name__}: {e})", started[c])
        finally:
            for f, _ in futures.values():
                f.cancel()
            if own:
                client.close()


def make_executor(name: str, jobs: int = 1, scheduler: str | None = None) -> Executor:
    """``local`` (processes), ``dask`` (needs ``scheduler``) or ``inline`` (this process)."""
    if name == "local":
        return LocalExecutor(jobs)
    if name == "dask":
        return DaskExecutor(scheduler)
    if name == "inline":
        return InlineExecutor()
    raise NimbusError(f"unknown executor {name!r}; use local or dask")


# --- the grid -------------------------------------------------------------------------------------
@dataclass
class GridOutcome:
    """What :func:`run_grid` did.

    Attributes
    ----------
    ran : list of dict
        Records of the cells this run ran (ok or error).
    skipped : list of str
        Ids of cells skipped because they already have an ``ok`` record.
    running_elsewhere : dict of str to str
        Ids of cells left to another live run that holds their lock, with who holds it.
    """

    ran: list[dict]
    skipped: list[str]
    running_elsewhere: dict[str, str] = dataclasses.field(default_factory=dict)

    @property
    def failed(self) -> list[dict]:
        return [r for r in self.ran if r.get("status") != "ok"]


def format_cell_line(rec: dict, i: int, n: int) -> str:
    """One progress line per finished cell."""
    head = f"[{i}/{n}] {rec['cell_id']}"
    if rec.get("status") != "ok":
        return f"{head}: ERROR {rec.get('error')}"

    def f(v, spec):
        return "n/a" if v is None else format(v, spec)

    return (f"{head}: PSNR {f(rec.get('psnr'), '.2f')} SSIM {f(rec.get('ssim'), '.3f')} "
            f"LPIPS {f(rec.get('lpips'), '.3f')}  train {f(rec.get('train_time_s'), '.1f')} s, "
            f"{rec.get('num_gaussians')} Gaussians")


def run_grid(cells: Sequence[Cell], root: str | os.PathLike, executor: Executor | None = None,
             options: CellOptions | None = None, rerun: bool = False, progress: bool = True,
             log: Callable[[str], None] | None = None) -> GridOutcome:
    """Prepare the data, run every unfinished cell, and append each record to the store as it arrives.

    Parameters
    ----------
    cells : sequence of Cell
    root : path
        Benchmark root (see the module docstring); an existing one is reused.
    executor : Executor, optional
        Default :class:`LocalExecutor` with one job.
    options : CellOptions, optional
    rerun : bool
        Run cells that already have an ``ok`` record too (a new ``ok`` record supersedes the old).
    progress : bool
        tqdm bar over cells on stderr.
    log : callable(str), optional
        Receives one line per finished cell and per preparation step (default: stderr).

    Returns
    -------
    GridOutcome
        Cells whose lock another live run holds are left to it (``running_elsewhere``).

    Raises
    ------
    NimbusError
        ``root`` is a file, lies under one, or cannot be written.
    """
    from tqdm import tqdm

    from nimbus.utils.fs import check_output_dir

    root = Path(root)
    check_output_dir(root, overwrite=True, flag="--root")  # a root is meant to be reused: not-empty is fine
    options = options or CellOptions()
    executor = executor or LocalExecutor()
    store = ResultsStore(root)
    locks: dict[str, FileLock] = {}
    bar = None
    try:
        skipped, elsewhere = _claim_cells(store, cells, rerun, locks)
        todo = [c for c in cells if c.cell_id in locks]
        bar = tqdm(total=len(todo), desc="cells", unit="cell", file=sys.stderr, disable=not progress or not todo,
                   dynamic_ncols=True)
        say = log or (lambda s: bar.write(s, file=sys.stderr))
        if skipped:
            say(f"skipping {len(skipped)} finished cell(s) already in {store.path}")
        if elsewhere:
            say(f"leaving {len(elsewhere)} cell(s) to another run on {root} that is running them "
                f"({'; '.join(sorted(set(elsewhere.values())))}): {', '.join(elsewhere)}")
        ran = []
        if todo:
            prepare_data(root, todo, progress=False, log=say)
            records = executor.imap(todo, str(root), options)
            try:
                for rec in records:
                    store.append(rec)
                    lock = locks.pop(rec["cell_id"], None)
                    if lock is not None:  # only once its record is stored: a run that gets it then sees it done
                        lock.release()
                    ran.append(rec)
                    say(format_cell_line(rec, len(ran), len(todo)))
                    bar.update(1)
            finally:
                # Stop the executor (its workers may still write run folders) before the locks go.
                close = getattr(records, "close", None)
                if close is not None:
                    close()
    finally:
        for lock in locks.values():
            lock.release()
        if bar is not None:
            bar.close()
    return GridOutcome(ran, skipped, elsewhere)


def _claim_cells(store: ResultsStore, cells: Sequence[Cell], rerun: bool,
                 locks: dict[str, FileLock]) -> tuple[list[str], dict[str, str]]:
    """Take the lock of every cell to run into ``locks``; the ids skipped as finished, and those held elsewhere.

    The store is read again once the locks are held: a cell that another run finished after
    the first look (its record is stored before its lock is released) is skipped, not rerun
    over that run's finished folder.
    """
    done = set() if rerun else store.finished()
    elsewhere = {}
    for c in cells:
        if c.cell_id in done or c.cell_id in locks:
            continue
        lock = store.cell_lock(c.cell_id)
        if lock.acquire():
            locks[c.cell_id] = lock
        else:
            holder = lock.holder()
            elsewhere[c.cell_id] = holder.describe() if holder else "another process"
    if not rerun:
        done = store.finished()
        for cid in [cid for cid in locks if cid in done]:
            locks.pop(cid).release()
        elsewhere = {cid: h for cid, h in elsewhere.items() if cid not in done}
    return [c.cell_id for c in cells if c.cell_id in done], elsewhere
