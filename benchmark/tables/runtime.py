"""The paper's model complexity / runtime table (``tab:runtime``), ours from the results store and the paper's.

Methods (H+R+S cells) as rows; Params. / Memory / Training / FPS as columns, in the paper's units,
each the mean over seeds, then over the scenes; a method missing a scene has no values.  Not
ranked (the paper marks nothing).  One table per preset when the store mixes presets.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

from benchmark.data import PAPER_ABLATIONS_DIR, read_csv
from benchmark.tables.ablation import LATEX_PACKAGES, by_preset
from benchmark.tables.model import Block, Column, LongFormat, Row, Table
from benchmark.tables.results import finished, ordered

if TYPE_CHECKING:  # importlib.resources.abc is Python 3.11+
    from importlib.resources.abc import Traversable

KEY, PAPER_LABEL, WEATHER, REFERENCE = "runtime", "tab:runtime", "H+R+S", "runtime.csv"
TITLE = f"Model complexity and runtime ({WEATHER})"
#: The columns in the paper's units; ``key`` is the column of the paper's ``runtime.csv``.  Decimals are
#: the paper's, more where a small value needs them (two significant digits).
COLUMNS = (
    Column("params_M", "Params.", "Params.", 1, unit="M", significant=2),
    Column("memory_G", "Memory", "Memory", 1, unit="G", significant=2),
    Column("training_min", "Training", "Training", 0, unit="min", significant=2),
    Column("fps", "FPS", "FPS", 0, significant=2),
)
#: Column key -> (store column, factor from the store's unit to the shown one).
FROM_STORE = {"params_M": ("num_params", 1e-6), "memory_G": ("peak_memory_mb", 1 / 1024),
              "training_min": ("train_time_s", 1 / 60), "fps": ("render_fps", 1.0)}
CSV = LongFormat("runtime.csv", "complexity / runtime, one row per method",
                 ("table", "weather", "preset", "method", *(c.key for c in COLUMNS), "runs", "scenes"))
NOTE = ("Params. = optimised parameter count; Memory = peak training memory (CUDA allocator peak on a GPU, "
        "process resident-set high-water mark on a CPU); Training = wall-clock training time; FPS = "
        "test-view rendering speed")
PAPER_NOTE = ("Params., Memory, Training and FPS denote parameter count, training memory usage, training time "
              "and rendering speed (the paper's caption)")


def _table(key: str, label: str, rows: list[Row], **kw) -> Table:
    """A table of this layout, ours or the paper's (``label``: the LaTeX label's stem)."""
    return Table(key, KEY, kw.pop("title"), COLUMNS, groups=[""], blocks=[Block(rows)], group_heads=False,
                 latex_packages=LATEX_PACKAGES, label=f"tab:nimbus-bench-{label.replace('_', '-')}", **kw)


def _runtime_table(frame, key: str, title: str, preset: str, method_order: Sequence[str]) -> Table:
    scenes = ordered(frame["scene_label"])
    rows: list[Row] = []
    notes: list[str] = []
    for m in ordered(frame["method"], method_order):
        g = frame[frame["method"] == m]
        row = Row(m, fields={"method": m, "runs": len(g)})
        have = ordered(g["scene_label"])
        for col in COLUMNS:
            store_column, scale = FROM_STORE[col.key]
            per_scene = [g[g["scene_label"] == s][store_column].astype(float) for s in have]
            complete = len(have) == len(scenes) and all(v.notna().all() for v in per_scene)
            row.values[("", col.key)] = float(np.mean([v.mean() for v in per_scene])) * scale if complete else None
        if len(have) < len(scenes):
            notes.append(f"{m} was run on {len(have)} of the {len(scenes)} scenes, so it has no values")
        rows.append(row)
    devices = sorted({str(r.get("device")) for r in frame["record"] if isinstance(r, dict) and r.get("device")})
    if len(devices) > 1:
        notes.append(f"the runs come from several devices ({', '.join(devices)}): their timings are not comparable")
    device = ", ".join(devices) if devices else "not recorded"
    notes.insert(0, f"{NOTE}; device: {device}; mean over seeds, then over the scenes ({', '.join(scenes)})")
    return _table(key, key, rows, title=title, notes=notes, what=f"ours: {title} (paper layout {PAPER_LABEL})",
                  csv=CSV, fields={"table": key, "weather": WEATHER, "preset": preset, "scenes": " ".join(scenes)})


def tables(df, method_order: Sequence[str] = ()) -> tuple[list[Table], list[str]]:
    """Our runtime table(s) from the store's finished H+R+S cells (one per preset), and ``[layout]`` when
    there are none.  Methods in ``method_order`` are listed first.
    """
    ok = finished(df)
    hybrid = ok[ok["weather"] == WEATHER]
    out = [_runtime_table(frame, key, title, preset, method_order)
           for key, title, preset, frame in by_preset(hybrid, KEY, TITLE)]
    return out, ([] if out else [f"{KEY} ({PAPER_LABEL})"])


def paper(folder: Traversable = PAPER_ABLATIONS_DIR) -> dict[str, Table]:
    """The paper's runtime table (``{"runtime": table}``; empty when its reference file is absent)."""
    path = folder / REFERENCE
    if not path.is_file():
        return {}
    records = read_csv(path)
    label = records[0]["table_label"]
    rows = [Row(r["method"], {("", c.key): float(r[c.key]) for c in COLUMNS}) for r in records]
    return {KEY: _table(f"paper_{KEY}", f"paper-{KEY}", rows,
                        title=f"the paper's reported numbers on the paper's data ({label}: {TITLE})",
                        notes=[f"Transcribed from nimbusgs.tex {label}; NOT results of this benchmark (other scenes, "
                               f"the paper's GPU); {PAPER_NOTE}"])}
