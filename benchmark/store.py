"""The benchmark's results store: one JSON line per finished cell, and the locks that let runs share it.

Layout::

    ROOT/results.jsonl          one record per finished cell attempt (see :func:`benchmark.cell.run_cell`)
    ROOT/locks/<cell-id>.lock   held while a run works on that cell (:class:`FileLock`)
    ROOT/locks/data-<name>.lock held while a run renders or synthesises that scene's data

Which record counts
    A cell run twice (after an error, or with ``--rerun``) has several records.  The one
    that counts is the cell's latest ``ok`` record; a cell that never finished shows its
    latest record (an error).  A later error never hides a result: an error says that an
    attempt failed (a crash, a killed worker, a run another one disturbed), not that the
    earlier figures are wrong, so a failed retry must not throw a good result away.  A
    later ``ok`` supersedes an earlier one (``--rerun``).  To drop a result for good,
    delete its line from ``results.jsonl``.

What a record holds
    Its fields and their types are declared once, in :class:`nimbus.schemas.ResultRecord` (listed on
    the docs' Record schemas page); unknown fields are allowed.  A reader checks every line against it before
    using any field, and skips a line that is not JSON or does not fit, with a warning naming the line
    and the field (``results.jsonl line 7: field 'psnr' must be a number or null, got 'abc'``): one
    damaged line costs its cell, which reruns, not the whole store.  :meth:`ResultsStore.append` refuses
    to write a record that would not fit.

Several runs on one root
    Two ``nimbus-bench run`` (or ``tradeoff``) on one root share it safely.  A run holds
    the lock of every cell it works on, from before it looks at the cell's folders until
    the cell's record is in the store; a second run skips cells whose lock is held
    ("running elsewhere") and never touches their folders.  The locks are
    ``fcntl.flock`` locks, which the kernel drops when the holding process ends however
    it ends, so the lock of a killed run is free at once; the file only names the holder
    (pid, host, start time) for messages.  On NFS this needs a mount with locking
    (the default); the workers of a Dask run do not lock, their parent does.

Crash safety
    A record is serialised first, then appended with one ``os.write`` of the whole line
    (``O_APPEND``) while holding an exclusive lock on the file, then ``fsync``-ed, so
    lines of concurrent writers never interleave and a killed run leaves at worst a
    truncated *last* line.  Readers ignore a last line that is not complete JSON; the
    writer cuts such a line off (under the same lock) before appending, so a torn
    record can never be glued to the next one.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import socket
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterable, Iterator

from nimbus.errors import NimbusError, SkippedRecordWarning
from nimbus.schemas import ResultRecord, parse_json, problem
from nimbus.utils.fs import confined_path, refuse_nonfinite_record, shown, single_name

STORE_FILE = "results.jsonl"
LOCK_DIR = "locks"
#: Columns of :func:`load_results` taken from each record as is (the rest stay in ``record``).
SCALAR_COLUMNS = (
    "cell_id", "scene", "size", "weather", "method", "preset", "seed", "status", "error",
    "psnr", "ssim", "lpips", "input_psnr", "input_ssim", "input_lpips", "ssim_protocol", "lpips_net",
    "train_time_s", "peak_memory_mb", "num_gaussians", "num_params", "render_fps", "iterations", "config_hash",
    "input_sha256", "started_at", "finished_at", "scene_path", "scene_hash", "scene_kind",
)
#: Bad lines of a store warned about one by one; past this many, one warning counts the rest.
MAX_WARNED_LINES = 10
# flock fails with these where the file system has no locking (an NFS mount with nolock, some FUSE).
_NO_LOCKING = (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS)


def store_path(root: str | os.PathLike) -> Path:
    """The results file of a benchmark root (``ROOT/results.jsonl``)."""
    return Path(root) / STORE_FILE


def require_store(root: str | os.PathLike) -> Path:
    """``ROOT/results.jsonl``, or NimbusError with what to do when it is missing or unreadable."""
    root, store = Path(root), store_path(root)
    try:
        if root.exists() and not root.is_dir():
            raise NimbusError(f"--root {root} is a file; give the benchmark folder that holds results.jsonl")
        if not store.is_file():
            raise NimbusError(f"{store} does not exist; run `nimbus-bench run --root {root}` first")
    except PermissionError:
        raise NimbusError(f"--root {root} cannot be read (permission denied); give read access or choose another "
                          "--root") from None
    return store


def record_run_dir(root: str | os.PathLike, record: dict) -> Path:
    """``ROOT/<run_dir>`` of a record: its run folder, refused (NimbusError naming the cell and the field)
    unless it resolves inside the root (an absolute path, ``..`` or a link leading out would make a
    reader read, and the report copy, files from anywhere)."""
    run_dir = record.get("run_dir")
    with _edited_record():
        confined_path(root, run_dir, f"{STORE_FILE} record {record.get('cell_id')!r}: 'run_dir'")
    return Path(root) / run_dir


#: The size of a scene read from a folder at full resolution (``images/``): its data is named after the folder alone.
FOLDER_SIZE = "images"


def data_name_of(scene: str, size: str) -> str:
    """The name of a scene's data folders: ``<scene>-<size>`` (``garden-tiny``, ``bicycle-images_4``), or the
    folder's name alone for a folder scene at full resolution (size :data:`FOLDER_SIZE`)."""
    return scene if size == FOLDER_SIZE else f"{scene}-{size}"


def record_data_name(record: dict) -> str:
    """:func:`data_name_of` a record, the name of its data folders (``ROOT/data/<name>``, ``ROOT/scenes/<name>``);
    scene and size must each be a single file name (:func:`nimbus.utils.fs.single_name`), else NimbusError naming it."""
    where = f"{STORE_FILE} record {record.get('cell_id')!r}"
    with _edited_record():
        return data_name_of(*(single_name(record.get(k), f"{where}: {k!r}") for k in ("scene", "size")))


@contextlib.contextmanager
def _edited_record() -> Iterator[None]:
    """Add what to do to a refusal of a record's field: nimbus-bench never writes such a record."""
    try:
        yield
    except NimbusError as e:
        raise NimbusError(f"{e}. The store was edited by hand or corrupted: delete that record's line from "
                          f"{STORE_FILE} and rerun the cell") from None


def counting_records(records: Iterator[dict] | list[dict]) -> dict[str, dict]:
    """The record that counts for each cell, by ``cell_id`` (module docstring, "Which record counts").

    The latest ``ok`` record of a cell; for a cell without one, its latest record.
    """
    out: dict[str, dict] = {}
    for rec in records:
        cid = rec["cell_id"]
        if rec.get("status") == "ok" or out.get(cid, {}).get("status") != "ok":
            out[cid] = rec
    return out


class ResultsStore:
    """Append-only JSON Lines store of cell records under a benchmark root.

    Parameters
    ----------
    root : path
        Benchmark root folder (created on the first append).
    """

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)
        self.path = store_path(root)

    # --- reading -----------------------------------------------------------------------
    def records(self) -> list[dict]:
        """Every complete record, in file order.

        Each line is checked against :class:`nimbus.schemas.ResultRecord`; a line that is not JSON or does
        not fit is skipped with a warning naming the line and the field, and so is a truncated last line.
        A ``cell_id`` that is not a single file name is refused (NimbusError): it would name a path.
        """
        return list(_read_lines(self.path))

    def latest(self) -> dict[str, dict]:
        """The record that counts for each cell, by ``cell_id``: its latest ``ok`` one, else its latest one."""
        return counting_records(self.records())

    def finished(self) -> set[str]:
        """Cell ids with an ``ok`` record (what a resumed run skips)."""
        return {cid for cid, rec in self.latest().items() if rec.get("status") == "ok"}

    # --- writing -----------------------------------------------------------------------
    def append(self, record: dict) -> None:
        """Append one record durably: one ``os.write`` of the whole line under an exclusive lock, then fsync.

        A torn last line (a writer killed mid-write) is cut off first, under the same lock, so
        it can never be glued to this record and no concurrent writer's line is cut instead.
        """
        if "cell_id" in record:  # a non-finite score: one line naming the field (NimbusError)
            refuse_nonfinite_record(record, f"a record of cell {shown(record['cell_id'])} to {self.path}")
        why = problem(ResultRecord, record)
        if why is not None:  # a writer's bug: such a line would be skipped by every reader
            raise ValueError(f"a results record {why} (nimbus.schemas.ResultRecord)")
        line = (json.dumps(record, sort_keys=True, allow_nan=False) + "\n").encode()
        self.root.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            _flock(fd, fcntl.LOCK_EX, self.path)
            self._repair_tail(fd)
            written = os.write(fd, line)
            if written != len(line):  # a full disk; the next append cuts the partial line off
                raise OSError(errno.ENOSPC, f"{self.path}: wrote {written} of {len(line)} bytes of a record")
            os.fsync(fd)
        finally:
            os.close(fd)  # also drops the lock

    def _repair_tail(self, fd: int) -> None:
        """Cut off a last line without its newline: the remains of a write a crash interrupted."""
        size = os.fstat(fd).st_size
        if size == 0 or os.pread(fd, 1, size - 1) == b"\n":
            return
        content = os.pread(fd, size, 0)
        keep = content.rfind(b"\n") + 1
        os.ftruncate(fd, keep)
        os.fsync(fd)
        warnings.warn(f"{self.path}: dropped a truncated last record ({size - keep} bytes) left by an "
                      "interrupted run", stacklevel=3)

    # --- locks -------------------------------------------------------------------------
    def cell_lock(self, cell_id: str) -> "FileLock":
        """The lock a run holds while it works on a cell (its run folder and its record)."""
        return FileLock(self.root / LOCK_DIR / f"{cell_id}.lock")

    def data_lock(self, name: str) -> "FileLock":
        """The lock a run holds while it renders or synthesises the data of one scene (``garden-tiny``)."""
        return FileLock(self.root / LOCK_DIR / f"data-{name}.lock")


@dataclass(frozen=True)
class LockHolder:
    """Who holds a :class:`FileLock`, as its file records it.

    Attributes
    ----------
    pid : int
        Process id of the holder (on ``host``).
    host : str
        Host name of the holder.
    started_at : str
        When it took the lock (UTC, ISO 8601).
    """

    pid: int
    host: str
    started_at: str

    def describe(self) -> str:
        return f"pid {self.pid} on {self.host}, since {self.started_at}"


class FileLock:
    """An exclusive lock on a file (``fcntl.flock``) that one process at a time can hold.

    The kernel drops the lock when the holding process ends, however it ends, so a lock
    left behind by a killed run is free at once: its file (naming a dead process) is
    simply taken over.  A stale lock therefore never needs an age rule or a hand clean-up,
    unlike a lock that is a file's mere existence.  While held, the file records the holder
    (:class:`LockHolder`) so that a run that finds it taken can say by whom.  ``release``
    removes the file.

    Parameters
    ----------
    path : path
        The lock file (its folder is created on acquire).
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        """Whether this object holds the lock."""
        return self._fd is not None

    def acquire(self, wait: bool = False) -> bool:
        """Take the lock; True on success.  ``wait=False`` returns False at once when another holds it.

        Raises
        ------
        NimbusError
            The file system does not support locks.
        """
        if self._fd is not None:
            raise RuntimeError(f"{self.path} is already held by this lock object")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            try:
                if not _flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB), self.path):
                    os.close(fd)
                    return False
                # The previous holder removes the file on release; if it did so after we opened
                # it, we now lock a file no one else can see: start over on the current one.
                try:
                    current = os.path.samestat(os.fstat(fd), os.stat(self.path))
                except FileNotFoundError:
                    current = False
                if not current:
                    os.close(fd)
                    continue
                me = {"pid": os.getpid(), "host": socket.gethostname(),
                      "started_at": datetime.now(timezone.utc).isoformat(timespec="seconds")}
                os.ftruncate(fd, 0)
                os.pwrite(fd, (json.dumps(me) + "\n").encode(), 0)
            except BaseException:
                os.close(fd)
                raise
            self._fd = fd
            return True

    def release(self) -> None:
        """Give the lock up and remove its file (nothing happens when not held)."""
        if self._fd is None:
            return
        # Unlink while still holding the lock: a process that opened the file meanwhile finds it
        # unlinked once it gets the lock and starts over (see acquire), so no two hold at once.
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)
        os.close(self._fd)
        self._fd = None

    def holder(self) -> LockHolder | None:
        """The holder the file names (None when there is no file or it is being written)."""
        try:
            d = json.loads(self.path.read_text())
            return LockHolder(int(d["pid"]), str(d["host"]), str(d["started_at"]))
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def __enter__(self) -> "FileLock":
        self.acquire(wait=True)
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _flock(fd: int, op: int, path: Path) -> bool:
    """``fcntl.flock``; False when non-blocking and held elsewhere, NimbusError where there is no locking."""
    try:
        fcntl.flock(fd, op)
    except BlockingIOError:
        return False
    except OSError as e:
        if e.errno in _NO_LOCKING:
            raise NimbusError(f"the file system holding {path} does not support file locks ({e.strerror}), which "
                              "runs sharing a benchmark root need; put --root on a local disk or an NFS mount with "
                              "locking") from None
        raise
    return True


def _read_lines(path: Path) -> Iterator[dict]:
    try:
        if not path.is_file():
            if path.exists():
                raise NimbusError(f"{path} is not a file; a benchmark root holds its results in a results.jsonl file")
            return
        with open(path, "rb") as f:
            # A shared lock waits for an append in progress, so a record being written is not
            # mistaken for a torn one; where there is no locking, read anyway.
            with contextlib.suppress(OSError):
                fcntl.flock(f.fileno(), fcntl.LOCK_SH)
            data = f.read()
    except PermissionError:
        raise NimbusError(f"{path} cannot be read (permission denied); give read access or choose another "
                          "--root") from None
    lines = data.split(b"\n")
    # A complete file ends with a newline, so the last element is b"".  Anything else
    # there is a record a crash cut short: ignored, never half-parsed.
    *complete, tail = lines
    if tail.strip():
        warnings.warn(f"{path}: ignoring a truncated last line (an interrupted run); it is removed on the next "
                      "append", stacklevel=3)
    skipped = 0
    for i, raw in enumerate(complete, 1):
        if not raw.strip():
            continue
        try:
            rec = parse_json(raw)
            why = problem(ResultRecord, rec)
        except ValueError as e:
            why = f"is not valid JSON ({str(e)[:120]})"
        if why is not None:
            # One damaged line costs its cell, not the store: the rest still reads, and the cell reruns.
            skipped += 1
            if skipped <= MAX_WARNED_LINES:
                warnings.warn(f"{path} line {i}: {why}; skipped it. The store was edited by hand or corrupted: "
                              "fix or delete that line (rerun to recompute the cell)", SkippedRecordWarning,
                              stacklevel=3)
            continue
        # The id names the cell's run folder, lock and report thumbnails: one name, never a path.
        with _edited_record():
            single_name(rec["cell_id"], f"{path} line {i}: 'cell_id'")
        yield rec
    if skipped > MAX_WARNED_LINES:
        warnings.warn(f"{path}: skipped {skipped - MAX_WARNED_LINES} more records that do not fit the results "
                      "record schema (nimbus.schemas.ResultRecord)", SkippedRecordWarning, stacklevel=3)


def check_scene_hashes(records: Iterable[dict], where: str) -> None:
    """NimbusError when two records name one scene (name and size) with different ``scene_hash``."""
    seen: dict[str, tuple[str, str]] = {}
    for rec in records:
        h = rec.get("scene_hash")
        if not h:
            continue
        key = data_name_of(rec.get("scene"), rec.get("size"))
        if key in seen and seen[key][0] != h:
            raise NimbusError(f"{where} mixes two scenes named {rec.get('scene')!r} with different content "
                              f"({seen[key][1]}, hash {seen[key][0][:12]}; {rec.get('scene_path')}, hash {h[:12]}); "
                              "delete one scene's records or keep them in separate roots")
        seen.setdefault(key, (h, rec.get("scene_path", "")))


def load_results(root: str | os.PathLike, latest: bool = True, status: str | None = None):
    """The store as a pandas DataFrame, one row per record.

    Parameters
    ----------
    root : path
        Benchmark root (holding ``results.jsonl``) or the ``.jsonl`` file itself.
    latest : bool
        Keep only the record that counts for each cell (default: its latest ``ok`` record, else
        its latest one; see the module docstring); False keeps every record, in file order.
    status : {"ok", "error"}, optional
        Keep only records with this status.

    Returns
    -------
    pandas.DataFrame
        Columns :data:`SCALAR_COLUMNS` (missing values NaN / None; ``method`` is labelled by :func:`method_label` where the
        store holds it under more than one set of ``--set`` overrides) plus ``per_view``
        (list of dicts) and ``record`` (the full record dict).
    """
    import pandas as pd

    root = Path(root)
    store = ResultsStore(root.parent) if root.suffix == ".jsonl" else ResultsStore(root)
    if root.suffix == ".jsonl":
        store.path = root
    recs = list(store.latest().values()) if latest else store.records()
    check_scene_hashes(recs, str(store.path))
    if status is not None:
        recs = [r for r in recs if r.get("status") == status]
    settings: dict[str, set[str]] = {}
    for r in recs:
        settings.setdefault(r.get("method"), set()).add(json.dumps(r.get("overrides") or {}, sort_keys=True))
    rows = [{**{c: r.get(c) for c in SCALAR_COLUMNS}, "per_view": r.get("per_view"), "record": r,
             "method": method_label(r) if len(settings[r.get("method")]) > 1 else r.get("method")} for r in recs]
    return pd.DataFrame(rows, columns=[*SCALAR_COLUMNS, "per_view", "record"])


def method_label(record: dict) -> str:
    """A record's method with its ``--set`` overrides, if it had any (``nimbus[lambda_dehaze=0]``).

    :func:`load_results` labels a method's records so when the store holds that method under more than one set of
    overrides, so that a cell trained with other settings is never averaged into the method's row; a grid run
    whole with one ``--set`` keeps its methods' names.
    """
    overrides = record.get("overrides") or {}
    if not overrides:
        return record.get("method")
    return f"{record.get('method')}[{','.join(f'{k}={v}' for k, v in sorted(overrides.items()))}]"


def split_method_labels(spec: str) -> list[str]:
    """A comma list of methods and :func:`method_label` labels, split at the commas outside brackets only:
    ``"nimbus-paper[a=1,b=2],3dgs"`` -> ``["nimbus-paper[a=1,b=2]", "3dgs"]`` (a label's overrides are joined by
    commas too). Blank items are dropped."""
    items, depth, start = [], 0, 0
    for i, ch in enumerate(spec):
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth = max(depth - 1, 0)
        elif ch == "," and depth == 0:
            items.append(spec[start:i])
            start = i + 1
    items.append(spec[start:])
    return [item.strip() for item in items if item.strip()]


def export_parquet(root: str | os.PathLike, out: str | os.PathLike) -> Path:
    """Write the counting records' scalar columns (and per-view values as JSON text) as Parquet, atomically."""
    import io

    from nimbus.utils.fs import atomic_write_bytes

    df = load_results(root).drop(columns=["record"])
    df["per_view"] = df["per_view"].map(lambda v: json.dumps(v))
    buf = io.BytesIO()
    df.to_parquet(buf, index=False)
    return atomic_write_bytes(out, buf.getvalue())
