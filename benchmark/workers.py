"""Local worker processes for the benchmark grid: each one runs many cells, one at a time.

A cell of the default (tiny) benchmark trains for a few seconds, while a new Python process
needs as long again to import torch and
the compiled kernels, and scoring needs as long to load the LPIPS network.
:class:`CellWorkers` therefore starts ``jobs`` processes once and sends each of them cell after
cell: a worker trains the cell and renders its test views (:func:`benchmark.cell.train_cell`),
and the parent scores them (:func:`benchmark.cell.score_cell`) with one LPIPS network loaded
for the whole run, while that worker waits.  The LPIPS network (~0.4 GB resident) thus never
sits in a training process, whose peak memory is the cell's figure.

Start-up
    A worker is spawned (not forked: forking a process that has started torch's thread pools
    can deadlock), sets its torch threads, and loads what every cell would otherwise load on
    first use (:func:`benchmark.cell.warm_up`) before its first cell, so that no cell's
    training time includes it and every cell starts from the same resident baseline.  The
    first workers start before the parent prepares the data (:meth:`CellWorkers.start`), so that
    their start-up, and in a fresh checkout the kernels' build, runs beside it.

CUDA
    On CUDA every worker loads gsplat's extension, which gsplat builds on first use.  Several
    processes building it at once into the same folder removed each other's files (an H200 run of
    12 workers: 11 cells failed).  So before a CUDA run of several workers one process loads (and,
    the first time, builds) the extension alone (:func:`prebuild_extensions`), then the workers start.

Isolation
    A cell that raises is recorded failed by ``train_cell`` / ``score_cell`` themselves.  A worker that dies (killed,
    out of memory, a crash in native code) loses only the cell it was running: that cell is
    recorded failed, a new worker takes its place, and the other cells go on.

Peak memory
    The runner reports the process's resident-set high-water mark (``VmHWM``; see
    :func:`nimbus.train.runner.peak_memory_mb`).  Before each cell the worker frees what it can
    and resets that mark (Linux: ``5`` written to ``/proc/self/clear_refs``), so a cell's figure is
    the peak while it ran, over the warmed worker's baseline, never an earlier cell's peak.  Where
    the mark cannot be reset (no ``/proc``, not writable) a worker runs one cell and exits, and
    the next cell gets a fresh process, as every cell did before.
"""

from __future__ import annotations

import gc
import os
import threading
import time
from multiprocessing.connection import Connection, wait
from typing import Iterator, Sequence

from benchmark.cell import (Cell, CellOptions, error_record, runs_on_cuda, score_cell, train_cell, utc_now,
                            warm_up)
from nimbus.utils.memory import reset_peak_rss


def reset_peak_memory() -> bool:
    """Free what the last cell left and reset this process's peak memory; whether the peak was reset.

    A CUDA device's allocator peak is reset too when CUDA is in use.
    """
    import torch

    gc.collect()
    _trim_heap()
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
    return reset_peak_rss()


def _trim_heap() -> None:
    """Give the C heap's free pages back to the system (glibc), so a cell's baseline is what is in use."""
    import ctypes

    try:
        ctypes.CDLL(None).malloc_trim(0)  # this process's own symbols: libc's where it is glibc
    except (OSError, AttributeError):  # another C library: nothing to trim
        pass


def exit_with_parent(parent: int, poll_s: float = 1.0) -> threading.Thread:
    """Exit this process (status 1) within ``poll_s`` of its parent ``parent`` (a pid) ending.

    A worker learns that the parent is gone from its pipe only between cells, so a parent that was
    killed (``kill``, the machine's OOM killer) used to leave its workers training their cells to the
    end: an hour of a small NimbusGS cell, for nothing.  A daemon thread checks who the parent is.
    """
    def watch() -> None:
        while True:
            time.sleep(poll_s)
            if os.getppid() != parent:
                os._exit(1)

    thread = threading.Thread(target=watch, name="nimbus-exit-with-parent", daemon=True)
    thread.start()
    return thread


def serve(conn: Connection, parent: int | None = None, index: int = 0, options: CellOptions | None = None) -> None:
    """A worker's life: train each ``(cell, root, options)`` received, until ``None`` or the parent is gone.

    Warms up at once with ``options`` when given (a worker started before its cells' data is ready), else before
    its first cell, and again should the options change; exits after one cell
    where the peak memory cannot be reset between cells, and within a second of the parent
    process ``parent`` ending, even in the middle of a cell (:func:`exit_with_parent`).  Odd-numbered
    workers (``index``) load the compiled kernels in reverse order (:func:`~benchmark.cell.warm_up`).
    """
    if parent is not None:
        exit_with_parent(parent)
    try:
        _serve(conn, index, options)
    except KeyboardInterrupt:  # Ctrl-C reaches every process of the group: the parent says what happened
        return


def _serve(conn: Connection, index: int, options: CellOptions | None) -> None:
    warmed = None

    def warm(wanted: CellOptions) -> None:
        nonlocal warmed
        if wanted != warmed:
            warm_up(wanted, reverse=index % 2 == 1)
            warmed = wanted

    if options is not None:
        warm(options)
    while True:
        try:
            task = conn.recv()
        except EOFError:
            return
        if task is None:
            return
        cell, root, options = task
        warm(options)
        reusable = reset_peak_memory()
        conn.send((train_cell(cell, root, options), reusable))
        if not reusable:
            return


def prebuild_extensions(ctx, options: CellOptions) -> None:
    """Load (build, the first time) what a CUDA worker loads, in one process, before several workers start."""
    process = ctx.Process(target=warm_up, args=(options,), name="nimbus-bench-prebuild")
    process.start()
    process.join()  # what failed here fails again in the workers, which fall back or record why


class _Worker:
    """One spawned worker process, the pipe to it, and the cell it is running (None when idle)."""

    def __init__(self, ctx, index: int = 0, options: CellOptions | None = None) -> None:
        self.conn, child = ctx.Pipe()
        self.process = ctx.Process(target=serve, args=(child, os.getpid(), index, options),
                                   name="nimbus-bench-worker")
        self.process.start()
        child.close()
        self.index = index
        self.cell: Cell | None = None
        self.started_at: str | None = None
        #: The most cells running at once (this one's included) while its cell ran.
        self.at_once = 0
        #: False once it has said it takes no further cell (or died).
        self.reusable = True

    def send(self, cell: Cell, root: str, options: CellOptions) -> bool:
        """Hand it a cell; False when it has died meanwhile (the cell is not taken)."""
        try:
            self.conn.send((cell.to_dict(), root, options))
        except OSError:
            self.reusable = False
            return False
        self.cell, self.started_at = cell, utc_now()
        self.at_once = 1
        return True

    def result(self) -> dict:
        """The record of its cell as it sent it (trained, not scored), or a failure when it died without one."""
        cell, self.cell = self.cell, None
        try:
            if self.conn.poll():
                record, self.reusable = self.conn.recv()
                return {**record, "cells_at_once": self.at_once}
        except (EOFError, OSError):
            pass
        self.reusable = False
        self.process.join()
        code = self.process.exitcode
        how = f"killed by signal {-code}" if code is not None and code < 0 else f"exit status {code}"
        return error_record(cell, f"worker process died ({how}) while running the cell; out of memory? "
                                  "try fewer --jobs", self.started_at)

    def stop(self, timeout: float | None = None) -> None:
        """Ask it to exit after its current cell, and wait until it has (at most ``timeout`` seconds: a worker still
        warming up, say building the kernels, then exits once it is done, or with this process)."""
        try:
            self.conn.send(None)
        except OSError:  # it has exited already
            pass
        self.process.join(timeout)
        self.conn.close()


#: Seconds :meth:`CellWorkers.close` waits for an idle worker (one that has not finished warming up may take longer).
IDLE_STOP_S = 5.0
#: With a memory budget (``--jobs auto``), cells run at once before any has said how much memory it takes.
FIRST_WAVE = 2
#: The share of the budget that the workers' peaks may fill (the parent scores beside them, with LPIPS).
MEMORY_SHARE = 0.8


class CellWorkers:
    """Runs cells in ``jobs`` long-lived local worker processes, yielding each record as it comes back.

    Parameters
    ----------
    jobs : int
        Workers, i.e. cells running at once (at most one per cell).
    memory : int, optional
        Bytes the workers may take together (``--jobs auto``).  Until a cell's record has come back, at
        most :data:`FIRST_WAVE` workers run; then at most as many as :data:`MEMORY_SHARE` of ``memory`` holds at
        the largest peak (``peak_memory_mb``) a cell of this run has had.  A worker beyond that is stopped
        when its cell is done.  None: ``jobs`` workers from the start.

    Each record gets ``cells_at_once``: the most cells that ran at the same time while it trained (its
    ``train_time_s`` grows with them, as they share the memory bus).
    """

    def __init__(self, jobs: int, memory: int | None = None) -> None:
        self.jobs = jobs
        self.memory = memory
        #: The largest peak memory of a cell so far (MB), None before any record.
        self.peak_mb: float | None = None
        self._workers: list[_Worker] = []
        self._ctx = None

    def _context(self):
        import multiprocessing

        if self._ctx is None:
            self._ctx = multiprocessing.get_context("spawn")
        return self._ctx

    def _spawn(self, options: CellOptions | None = None) -> None:
        taken = {w.index for w in self._workers}
        index = next(i for i in range(len(self._workers) + 1) if i not in taken)
        self._workers.append(_Worker(self._context(), index, options))

    def start(self, cells: int, options: CellOptions) -> None:
        """Start the first workers for ``cells`` cells now, each loading at once what training needs (the first
        time, building the kernels: :func:`~benchmark.cell.warm_up`), while the caller prepares the cells' data.
        :meth:`imap` then hands them the cells; :meth:`close` stops them if it never comes."""
        while len(self._workers) < min(self.allowed(), cells):
            self._spawn(options)

    @property
    def started(self) -> bool:
        """Whether workers are running (started by :meth:`start`, or an :meth:`imap` in progress)."""
        return bool(self._workers)

    def close(self) -> None:
        """Stop every worker: one running a cell after that cell; an idle one is waited for at most
        :data:`IDLE_STOP_S` (a run whose data failed to prepare reports it without waiting for the kernels' build)."""
        workers, self._workers = self._workers, []
        for w in workers:
            w.stop(None if w.cell is not None else IDLE_STOP_S)

    def allowed(self) -> int:
        """Workers that may run now."""
        if self.memory is None:
            return self.jobs
        if self.peak_mb is None:
            return min(self.jobs, FIRST_WAVE)
        fits = int(MEMORY_SHARE * self.memory // (self.peak_mb * 2 ** 20)) if self.peak_mb > 0 else self.jobs
        return max(1, min(self.jobs, fits))

    def _note_peak(self, record: dict) -> None:
        peak = record.get("peak_memory_mb")
        if isinstance(peak, (int, float)) and peak == peak:
            self.peak_mb = max(self.peak_mb or 0.0, float(peak))

    def imap(self, cells: Sequence[Cell], root: str, options: CellOptions) -> Iterator[dict]:
        todo = list(cells)[::-1]  # taken from the end: table order
        if self.jobs > 1 and len(todo) > 1 and not self._workers and runs_on_cuda(options):
            prebuild_extensions(self._context(), options)
        workers = self._workers
        try:
            while True:
                for w in [w for w in workers if not w.reusable]:
                    w.stop()  # it died, or ran its one cell (the peak memory cannot be reset here)
                    workers.remove(w)
                for w in [w for w in workers if w.cell is None][:max(0, len(workers) - self.allowed())]:
                    w.stop()  # more workers than the memory holds at the cells' peak: one fewer
                    workers.remove(w)
                while todo and len(workers) < self.allowed():
                    self._spawn()
                for w in workers:
                    if w.cell is None and todo and w.send(todo[-1], root, options):
                        todo.pop()
                busy = [w for w in workers if w.cell is not None]
                for w in busy:
                    w.at_once = max(w.at_once, len(busy))
                if not busy:
                    if todo:
                        continue  # the idle workers had died: replaced above
                    break
                by_handle = {**{w.conn: w for w in busy}, **{w.process.sentinel: w for w in busy}}
                for handle in wait(list(by_handle)):
                    w = by_handle[handle]
                    if w.cell is not None:
                        record = w.result()
                        self._note_peak(record)
                        # Scored here while the worker waits: no cell trains beside its own scoring.
                        yield score_cell(record, root, options)
        finally:
            self.close()
