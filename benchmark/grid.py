"""The benchmark grid: cells (scene, weather, method, preset, seed) built, claimed and run by executors.

A cell, its data and its run are :mod:`benchmark.cell` (the root's layout is described
there); this module builds the list of cells, runs the unfinished ones through an executor
and stores each record as it comes back.

Executors
    :class:`LocalExecutor` trains cells in ``--jobs N`` local worker processes that each train
    many cells, paying torch's start-up once, and scores them in the parent with one LPIPS
    network (a dead worker costs only its cell; each cell's peak memory is its own:
    :mod:`benchmark.workers`); :class:`DaskExecutor` submits each cell as a task to a Dask
    distributed cluster (the workers must see ``ROOT`` on a shared file system).  Either way
    each cell runs through :func:`benchmark.cell.run_cell` (locally as its two halves,
    ``train_cell`` and ``score_cell``), and only the parent process writes the store, as each
    cell's record comes back.

Resumption
    A cell with an ``ok`` record is skipped (a later error record never hides it; see
    :mod:`benchmark.store`).  A killed cell leaves only its ``.partial`` run folder, which a
    rerun removes (:func:`benchmark.cell.clear_run_dirs`).

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
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator, Protocol, Sequence

from benchmark.cell import (CEILING, CEILING_METHOD, DEFAULT_SIZE, Cell, CellOptions, error_record, make_config,
                            prepare_data, run_cell, runs_on_cuda, utc_now)
from benchmark.store import FileLock, ResultsStore, data_name_of
from nimbus.errors import NimbusError
from nimbus.utils.cpus import usable_cpus

if TYPE_CHECKING:
    from benchmark.scene_sources import SceneSource

#: Methods of the default benchmark, in table order (those not registered are skipped): NimbusGS, plain 3DGS,
#: and the two-stage restore-then-3DGS baseline.
DEFAULT_METHODS = ("nimbus", "3dgs", "restore-3dgs")


# --- cells -------------------------------------------------------------------------------
def resolve_methods(spec: str | None) -> tuple[list[str], list[str]]:
    """Method names to run and the default ones skipped because they are not registered.

    ``spec`` None (or ``"default"``) is :data:`DEFAULT_METHODS`, keeping the registered ones;
    an explicit comma list must name registered methods only (NimbusError otherwise).
    """
    from nimbus.methods.registry import METHODS, get_method

    if spec is None or spec.strip() == "default":
        names = [m for m in DEFAULT_METHODS if m in METHODS]
        return names, [m for m in DEFAULT_METHODS if m not in METHODS]
    names = split_names(spec, "--methods")
    for n in names:
        get_method(n)
    return names, []


def split_names(spec: str, what: str) -> list[str]:
    out = []
    for item in spec.split(","):
        item = item.strip()
        if item and item not in out:
            out.append(item)
    if not out:
        raise NimbusError(f"{what} is empty; give a comma-separated list")
    return out


def build_cells(scenes: Sequence["str | SceneSource"], weathers: Sequence[str], methods: Sequence[str],
                presets: Sequence[str], seeds: Sequence[int], size: str = DEFAULT_SIZE,
                overrides: dict[str, str] | None = None, ceiling: bool = False) -> list[Cell]:
    """Every combination, in table order (scene, weather, method, preset, seed); validated before any work.

    ``scenes`` are built-in names (at ``size``) or :class:`~benchmark.scene_sources.SceneSource`
    (:func:`~benchmark.scene_sources.resolve_scenes`); a degraded dataset tree gets the cells of the
    weathers it has (its settings as given: the default family only).

    With ``ceiling``, each scene's cells are preceded by its clean-ceiling cells
    (:data:`~benchmark.cell.CEILING`): 3DGS on the clean scene, one per preset and seed, with the
    same ``overrides``; one per scene, however many weathers and methods the grid has.

    Raises
    ------
    NimbusError
        Unknown scene, size, weather (``H+R``, ``H+R@physical``: :mod:`weather_synth.settings`), method
        or preset, a negative seed, an override the method's config (or, with ``ceiling``, 3DGS's) does
        not have, or a dataset tree with none of the weathers (or asked for another protocol family).
    """
    from benchmark.scene_sources import TREE, SceneSource
    from nimbus.data.builtin import get_scene, get_size
    from nimbus.methods.registry import get_method
    from weather_synth.settings import parse_family_setting

    sources = [s if isinstance(s, SceneSource) else SceneSource(s, "builtin", size) for s in scenes]
    if any(s.kind == "builtin" for s in sources):
        get_size(size)
    for s in sources:
        if s.kind == "builtin":
            get_scene(s.name)
    weathers = [parse_family_setting(w).name for w in weathers]
    for seed in seeds:
        if seed < 0:
            raise NimbusError(f"seeds must be non-negative, got {seed}")
    ov = tuple(sorted((overrides or {}).items()))
    for m in methods:
        for p in presets:
            make_config(get_method(m), p, dict(ov))  # a bad preset or --set fails here, not in a worker
    if ceiling and CEILING_METHOD not in methods:
        for p in presets:
            try:
                make_config(get_method(CEILING_METHOD), p, dict(ov))
            except NimbusError as e:
                raise NimbusError(f"{e} (the clean ceiling trains {CEILING_METHOD} with the grid's preset and --set; "
                                  "pass --no-ceiling to run without it)") from None

    def scene_weathers(src: SceneSource) -> list[str]:
        if src.kind != TREE:
            return weathers
        has = dict(src.settings)
        other = [w for w in weathers if "@" in w]
        if other:
            raise NimbusError(f"{src.path}: a degraded dataset is scored as given, in its own weather; "
                              f"{', '.join(other)} names another synthesis family: drop it for this scene")
        mine = [w for w in weathers if w in has]
        if not mine:
            raise NimbusError(f"{src.path}: scene {src.name} has none of the weathers {', '.join(weathers)}; it has "
                              f"{', '.join(has)} (pass --weathers {','.join(has)} or all)")
        return mine

    # A name or seed given twice is one cell: two copies of a cell would train into one run folder at once.
    return list(dict.fromkeys(c for src in sources for c in [
        *(Cell(src.name, CEILING, CEILING_METHOD, p, int(seed), src.size, ov) for p in presets for seed in seeds
          if ceiling),
        *(Cell(src.name, w, m, p, int(seed), src.size, ov) for w in scene_weathers(src) for m in methods
          for p in presets for seed in seeds)]))


# --- executors -----------------------------------------------------------------------------------
class Executor(Protocol):
    """Runs cells and yields their records as they finish (in any order).

    :func:`run_grid` also calls ``start(cells, options)`` before it prepares the cells' data and ``close()`` when the
    run ends, where an executor has them (:class:`LocalExecutor`: its workers warm up meanwhile).
    """

    def imap(self, cells: Sequence[Cell], root: str, options: CellOptions) -> Iterator[dict]: ...


class InlineExecutor:
    """Runs cells one after the other in this process (debugging; tests)."""

    name = "inline"

    def imap(self, cells: Sequence[Cell], root: str, options: CellOptions) -> Iterator[dict]:
        for c in cells:
            yield run_cell(c, root, options)


#: ``--jobs auto``: as many workers as cores and memory allow, one torch thread each (:class:`LocalExecutor`).
AUTO_JOBS = "auto"


class LocalExecutor:
    """Runs cells in local worker processes, each running many cells (:class:`benchmark.workers.CellWorkers`).

    Parameters
    ----------
    jobs : int or "auto"
        Cells run at once (default 1).  Each worker gets ``max(1, cores // jobs)`` torch threads, counting
        the cores this process may run on (:func:`nimbus.utils.cpus.usable_cpus`: a ``taskset`` or a
        scheduler's CPU set, not the machine's count).

        ``"auto"`` (``nimbus-bench run``'s default) on the CPU: one worker per core with one torch thread
        each, at most one worker per cell (fewer cells than cores share the cores out), and no more than
        the memory holds: until a cell has finished at most two run at once, then as many as fit in the
        memory available at the start (:func:`nimbus.utils.memory.available_memory`) at the largest peak a
        cell has had so far.  Separate processes scale where threads do not (a step's parallel sections are
        short), and one thread a cell makes its figures independent of how many cores the machine has (given
        as many cells as cores).  On CUDA, ``"auto"`` is one worker with every core, as ``jobs=1``.
    """

    name = "local"

    def __init__(self, jobs: int | str = 1) -> None:
        self._workers = None  # the CellWorkers of the current run
        if jobs == AUTO_JOBS:
            self.jobs: int | None = None
            return
        if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
            raise NimbusError(f"--jobs must be auto or at least 1, got {jobs}")
        self.jobs = jobs

    def workers(self, cells: int | None = None) -> int:
        """Workers for ``cells`` cells (``auto``: one per core, at most one per cell; before the memory's say)."""
        if self.jobs is not None:
            return self.jobs
        return max(1, min(usable_cpus(), cells if cells is not None else usable_cpus()))

    def threads(self, cells: int | None = None) -> int:
        """Torch threads of each worker: the cores shared among the workers."""
        return max(1, usable_cpus() // self.workers(cells))

    def _pool(self, cells: Sequence[Cell], options: CellOptions):
        """The workers for ``cells`` (those :meth:`start` started, else new ones sized for ``cells``) and the options
        they run with."""
        from benchmark.workers import CellWorkers
        from nimbus.utils.memory import available_memory

        if options.threads is None:
            options = dataclasses.replace(options, threads=self.threads(len(cells)))
        if self._workers is None or not self._workers.started:
            memory = available_memory() if self.jobs is None else None
            self._workers = CellWorkers(self.workers(len(cells)), memory=memory)
        return self._workers, options

    def start(self, cells: Sequence[Cell], options: CellOptions) -> None:
        """Start the workers for ``cells`` now: they load what training needs (the first time, they build the
        compiled kernels) while the caller prepares the cells' data; :meth:`imap` then uses them.  On CUDA nothing
        starts early: gsplat's extension is built by one process before the workers (:mod:`benchmark.workers`)."""
        if runs_on_cuda(options):
            return
        workers, options = self._pool(cells, options)
        workers.start(len(cells), options)

    def close(self) -> None:
        """Stop the workers still running (a run that stopped before :meth:`imap`, or after it)."""
        if self._workers is not None:
            self._workers.close()
            self._workers = None

    def imap(self, cells: Sequence[Cell], root: str, options: CellOptions) -> Iterator[dict]:
        if self.jobs is None and runs_on_cuda(options):
            return LocalExecutor(1).imap(cells, root, options)
        workers, options = self._pool(cells, options)
        return workers.imap(cells, root, options)


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
                started[c] = utc_now()
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


def make_executor(name: str, jobs: int | str = 1, scheduler: str | None = None) -> Executor:
    """``local`` (processes), ``dask`` (needs ``scheduler``) or ``inline`` (this process)."""
    if name == "local":
        return LocalExecutor(jobs)
    if name == "dask":
        return DaskExecutor(scheduler)
    if name == "inline":
        return InlineExecutor()
    raise NimbusError(f"unknown executor {name!r}; use local or dask")


# --- command-line flags of the verbs that run cells (``run``, ``tradeoff``) ------------------------
def jobs_arg(value: str) -> int | str:
    """``--jobs``: ``auto`` or a number of workers (checked by :class:`LocalExecutor`)."""
    import argparse

    if value.strip().lower() == AUTO_JOBS:
        return AUTO_JOBS
    try:
        return int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expects auto or a positive number of workers, got {value!r}") from None


def add_run_arguments(p, jobs_help: str, jobs_default: int | str = 1) -> None:
    """The flags that say where and how cells run and are scored, and how the run reports."""
    from benchmark.metrics import EVAL_PROTOCOLS
    from nimbus.metrics import LPIPS_NETS, SSIM_PROTOCOLS

    p.add_argument("--executor", choices=("local", "dask"), default="local",
                   help="local: worker processes; dask: tasks on a Dask distributed cluster")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS", help="Dask scheduler address (with --executor dask)")
    p.add_argument("--jobs", type=jobs_arg, default=jobs_default, metavar="{auto,N}", help=jobs_help)
    p.add_argument("--protocol", choices=tuple(EVAL_PROTOCOLS), default="default",
                   help="; ".join(f"{k}: {v.summary}" for k, v in EVAL_PROTOCOLS.items()))
    p.add_argument("--ssim", choices=tuple(SSIM_PROTOCOLS), default="3dgs", help="SSIM protocol (3dgs: paper)")
    p.add_argument("--lpips", choices=LPIPS_NETS + ("none",), default="vgg", help="LPIPS network (vgg: paper)")
    p.add_argument("--device", default=None, help="torch device for training (default: cuda if available, else cpu)")
    p.add_argument("--rerun", action="store_true",
                   help="run finished cells again (a new result supersedes the old; a failed retry keeps the old one)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def executor_from_args(args) -> Executor:
    """The executor :func:`add_run_arguments`' flags name."""
    return make_executor(args.executor, args.jobs, args.scheduler)


def options_from_args(args) -> CellOptions:
    """The :class:`CellOptions` :func:`add_run_arguments`' flags name (``--protocol paper`` fixes SSIM and LPIPS)."""
    from benchmark.metrics import get_eval_protocol

    protocol = get_eval_protocol(getattr(args, "protocol", "default"))
    for flag, fixed, given in (("--ssim", protocol.ssim, args.ssim), ("--lpips", protocol.lpips, args.lpips)):
        if fixed is not None and given not in (fixed, "none"):  # none: leave LPIPS out (faster), said in the record
            raise NimbusError(f"--protocol {protocol.name} scores with {flag} {fixed}; drop {flag} {given} "
                              "(or use --protocol default)")
    return CellOptions(ssim_protocol=args.ssim, lpips_net=None if args.lpips == "none" else args.lpips,
                       device=args.device, eval_protocol=protocol.name)


def say_failed(outcome: "GridOutcome", root) -> None:
    """Tell stderr how many cells failed and how to retry them (nothing when none failed)."""
    if outcome.failed:
        print(f"{len(outcome.failed)} cell(s) failed; rerun the same command to retry them "
              f"(errors are in {root}/results.jsonl)", file=sys.stderr)


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
            start = getattr(executor, "start", None)
            if start is not None:  # the workers warm up (and build the kernels) while the data is prepared
                start(todo, options)
            prepare_data(root, todo, progress=False, log=say)
            scene_fields = {c.data_name: _scene_fields(root, c.data_name) for c in todo}
            records = executor.imap(todo, str(root), options)
            try:
                for rec in records:
                    rec = {**rec, **scene_fields.get(data_name_of(rec.get("scene"), rec.get("size")), {})}
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
        stop_executor = getattr(executor, "close", None)
        if stop_executor is not None:  # workers started for data that failed to prepare, say
            stop_executor()
        for lock in locks.values():
            lock.release()
        if bar is not None:
            bar.close()
    return GridOutcome(ran, skipped, elsewhere)


def _scene_fields(root: Path, data_name: str) -> dict:
    """``scene_path`` and ``scene_hash`` of a scene of the root (:mod:`benchmark.scene_sources`)."""
    from benchmark.scene_sources import builtin_fields, load_source

    source = load_source(root, data_name)
    return source.record_fields() if source is not None else builtin_fields(root, data_name)


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
