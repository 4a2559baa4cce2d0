"""The benchmark's results store: one JSON line per finished cell, appended crash-safely.

Layout: ``ROOT/results.jsonl``.  Each line is one record (see :func:`benchmark.grid.run_cell`
for the fields); a cell run twice (after an error, or with ``--rerun``) has several
records, and the last one counts.

Crash safety
    Only one process writes the store (the grid runner's parent).  A record is
    serialised first, then written with a single ``write`` of the whole line followed by
    ``flush`` and ``fsync``, so a killed run leaves at worst a truncated *last* line.
    Readers ignore a last line that is not complete JSON; the writer cuts such a line
    off before appending, so a torn record can never be glued to the next one.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any, Iterator

from nimbus.errors import NimbusError

STORE_FILE = "results.jsonl"
RECORD_FORMAT = "nimbus-bench-cell/1"
#: Columns of :func:`load_results` taken from each record as is (the rest stay in ``record``).
SCALAR_COLUMNS = (
    "cell_id", "scene", "size", "weather", "method", "preset", "seed", "status", "error",
    "psnr", "ssim", "lpips", "ssim_protocol", "lpips_net", "train_time_s", "peak_memory_mb",
    "num_gaussians", "num_params", "render_fps", "iterations", "config_hash", "input_sha256",
    "started_at", "finished_at",
)


def store_path(root: str | os.PathLike) -> Path:
    """The results file of a benchmark root (``ROOT/results.jsonl``)."""
    return Path(root) / STORE_FILE


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
        """Every complete record, in file order; a truncated last line is skipped (with a warning)."""
        return list(_read_lines(self.path))

    def latest(self) -> dict[str, dict]:
        """The last record of each cell, by ``cell_id``."""
        out: dict[str, dict] = {}
        for rec in self.records():
            out[rec["cell_id"]] = rec
        return out

    def finished(self) -> set[str]:
        """Cell ids whose last record has ``status == "ok"`` (what a resumed run skips)."""
        return {cid for cid, rec in self.latest().items() if rec.get("status") == "ok"}

    # --- writing -----------------------------------------------------------------------
    def append(self, record: dict) -> None:
        """Append one record durably (one write, flush, fsync); repairs a torn last line first."""
        if "cell_id" not in record:
            raise ValueError("a record needs a cell_id")
        line = (json.dumps(record, sort_keys=True, allow_nan=False) + "\n").encode()
        self.root.mkdir(parents=True, exist_ok=True)
        self._repair_tail()
        with open(self.path, "ab") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())

    def _repair_tail(self) -> None:
        """Cut off a last line without its newline: the remains of a write a crash interrupted."""
        if not self.path.exists() or self.path.stat().st_size == 0:
            return
        with open(self.path, "rb+") as f:
            f.seek(-1, os.SEEK_END)
            if f.read(1) == b"\n":
                return
            f.seek(0)
            content = f.read()
            keep = content.rfind(b"\n") + 1
            f.truncate(keep)
            f.flush()
            os.fsync(f.fileno())
        warnings.warn(f"{self.path}: dropped a truncated last record ({len(content) - keep} bytes) left by an "
                      "interrupted run", stacklevel=3)


def _read_lines(path: Path) -> Iterator[dict]:
    if not path.exists():
        return
    lines = path.read_bytes().split(b"\n")
    # A complete file ends with a newline, so the last element is b"".  Anything else
    # there is a record a crash cut short: ignored, never half-parsed.
    *complete, tail = lines
    if tail.strip():
        warnings.warn(f"{path}: ignoring a truncated last line (an interrupted run); it is removed on the next "
                      "append", stacklevel=3)
    for i, raw in enumerate(complete, 1):
        if not raw.strip():
            continue
        try:
            rec = json.loads(raw)
        except json.JSONDecodeError as e:
            raise NimbusError(f"{path} line {i} is not valid JSON ({e.msg}); the store was edited or corrupted "
                              "by hand: delete that line and rerun to recompute the cell") from None
        if not isinstance(rec, dict) or "cell_id" not in rec:
            raise NimbusError(f"{path} line {i} is not a benchmark record; delete it and rerun")
        yield rec


def load_results(root: str | os.PathLike, latest: bool = True, status: str | None = None):
    """The store as a pandas DataFrame, one row per record.

    Parameters
    ----------
    root : path
        Benchmark root (holding ``results.jsonl``) or the ``.jsonl`` file itself.
    latest : bool
        Keep only the last record of each cell (default); False keeps every record.
    status : {"ok", "error"}, optional
        Keep only records with this status.

    Returns
    -------
    pandas.DataFrame
        Columns :data:`SCALAR_COLUMNS` (missing values NaN / None) plus ``per_view``
        (list of dicts) and ``record`` (the full record dict).
    """
    import pandas as pd

    root = Path(root)
    store = ResultsStore(root.parent) if root.suffix == ".jsonl" else ResultsStore(root)
    if root.suffix == ".jsonl":
        store.path = root
    recs = list(store.latest().values()) if latest else store.records()
    if status is not None:
        recs = [r for r in recs if r.get("status") == status]
    rows = [{**{c: r.get(c) for c in SCALAR_COLUMNS}, "per_view": r.get("per_view"), "record": r} for r in recs]
    return pd.DataFrame(rows, columns=[*SCALAR_COLUMNS, "per_view", "record"])


def export_parquet(root: str | os.PathLike, out: str | os.PathLike) -> Path:
    """Write the latest records' scalar columns (and per-view values as JSON text) as Parquet, atomically."""
    import io

    from nimbus.utils.fs import atomic_write_bytes

    df = load_results(root).drop(columns=["record"])
    df["per_view"] = df["per_view"].map(lambda v: json.dumps(v))
    buf = io.BytesIO()
    df.to_parquet(buf, index=False)
    return atomic_write_bytes(out, buf.getvalue())


def jsonable(obj: Any) -> Any:
    """Replace non-finite floats by None and numpy scalars by Python ones (strict JSON)."""
    from benchmark.score import jsonable as _jsonable

    return _jsonable(obj)
