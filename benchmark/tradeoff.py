"""The speed / accuracy trade-off sweep (``nimbus-bench tradeoff``): what each costly knob buys, and its price.

A sweep is one *base* cell (by default NimbusGS with the ``tiny`` preset on the tiny
built-in ``garden`` under haze + rain, ``H+R``) and one-knob-at-a-time variations of
it.  A knob is a config field, set through ``--set``-style overrides, so every
variation is an ordinary benchmark cell (:class:`benchmark.cell.Cell`): it runs through
:func:`benchmark.grid.run_grid`, lands in the results store, is skipped when finished
(a rerun resumes), and runs on Dask like any other cell.  A variation whose config
equals the base config *is* the base cell (run once, listed under every knob).

Knobs with default values (:data:`KNOBS`; "base" is the base config's value)::

    iterations       base x 1/2, 1, 2      the preset's whole schedule is rescaled with them
    train_downscale  1, 2, 4               train on images shrunk by this factor; test at full size
    ray_samples      base x 1/2, 1, 2      K, CSM samples per ray (NimbusGS)
    grid_resolution  base x 1/2, 1, 2      extinction-grid voxels per axis (NimbusGS)
    sh_degree        0, 1, 2, 3            colour SH degree (the preset raises the active degree
                                           by one every sh_degree_interval iterations)
    components       3dgs, csm, csm+plm, csm+plm+ggs, auto
                                           NimbusGS components (``+`` joins them, as ``,``
                                           separates values); ``3dgs`` is the 3DGS method
                                           itself, the no-component end (the base ``--set``
                                           overrides that 3DGS has are kept)

Any other config field is a knob too, given explicit values
(``--knob lambda_dssim=0.2,0.4``).  Without ``--knob`` the sweep uses every knob of
:data:`KNOBS` that the base method's config has.

Outputs (``--out``, default ``ROOT/tradeoff``), each written atomically::

    tradeoff.csv   one row per (knob, value): metrics, costs, Pareto flags (unrounded)
    tradeoff.md    the same table, rounded, with the sweep's settings
    tradeoff.png   2 x 2 panels: PSNR and LPIPS against training time and peak memory

The costs are the trainer's figures: ``train_time_s`` (wall-clock of the training loop,
without evaluation and scoring; cells running side by side with ``--jobs`` > 1 slow each
other down) and ``peak_memory_mb`` (the CUDA allocator's peak on a GPU, the worker
process's resident-set high-water mark on a CPU, Python and torch included).  The
Pareto front of a panel (:func:`pareto_front`) is the set of cells no other cell beats
on both axes at once: nothing is at least as cheap and at least as accurate with one of
the two strictly better, comparing the values as ``tradeoff.md`` prints them
(:data:`FRONT_DECIMALS`), so a difference below the printed precision does not count.
"""

from __future__ import annotations

import dataclasses
import io
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from benchmark.cell import DEFAULT_PRESET, DEFAULT_SIZE, Cell
from benchmark.tables import writer
from benchmark.tables.model import Block, Column, LongFormat, Row, Table
from nimbus.errors import NimbusError

DEFAULT_SCENE = "garden"
DEFAULT_WEATHER = "H+R"
DEFAULT_METHOD = "nimbus"
#: Values of the ``components`` knob that switch the method instead (the no-component end).
METHOD_VALUES = {"3dgs": "3dgs"}
HALF_BASE_DOUBLE = (0.5, 1.0, 2.0)
#: (quality metric, cost) of the plot's panels, row-major; quality higher-is-better for PSNR.
PANELS = (("psnr", "train_time_s"), ("psnr", "peak_memory_mb"), ("lpips", "train_time_s"),
          ("lpips", "peak_memory_mb"))
HIGHER_IS_BETTER = {"psnr": True, "lpips": False}
COST_NAMES = {"train_time_s": "time", "peak_memory_mb": "memory"}
#: Decimals the fronts compare at: those of tradeoff.md (as ``nimbus-bench tables`` ranks values as printed),
#: so a difference too small to print puts no cell on a front.
FRONT_DECIMALS = {"psnr": 2, "lpips": 3, "train_time_s": 1, "peak_memory_mb": 0}
AXIS_LABELS = {"psnr": "PSNR (dB) ↑", "lpips": "LPIPS ↓", "train_time_s": "training time (s)",
               "peak_memory_mb": "peak memory (MB)"}
PARETO_COLUMNS = tuple(f"on_pareto_{q}_{COST_NAMES[c]}" for q, c in PANELS)
CSV_COLUMNS = ("knob", "value", "base", "method", "cell_id", "status", "psnr", "ssim", "lpips", "train_time_s",
               "wall_time_s", "peak_memory_mb", "num_gaussians", "iterations", *PARETO_COLUMNS)
FILES = ("tradeoff.csv", "tradeoff.md", "tradeoff.png")


@dataclass(frozen=True)
class KnobSpec:
    """A knob with default values.

    Attributes
    ----------
    defaults : callable
        Base config value -> the knob's default values (the base value among them).
    doc : str
        One line for ``--help``.
    """

    defaults: Callable[[object], tuple]
    doc: str


def _times(factors: Sequence[float], minimum: int = 1) -> Callable[[object], tuple]:
    def values(base) -> tuple:
        return tuple(dict.fromkeys(max(int(round(float(base) * f)), minimum) for f in factors))

    return values


KNOBS: dict[str, KnobSpec] = {
    "iterations": KnobSpec(_times(HALF_BASE_DOUBLE), "training iterations, base x 1/2, 1, 2 (schedule rescaled)"),
    "train_downscale": KnobSpec(lambda base: (1, 2, 4), "train on images shrunk 1, 2, 4 x (test at full size)"),
    "ray_samples": KnobSpec(_times(HALF_BASE_DOUBLE), "K, CSM samples per ray, base x 1/2, 1, 2"),
    "grid_resolution": KnobSpec(_times(HALF_BASE_DOUBLE, minimum=2), "extinction grid per axis, base x 1/2, 1, 2"),
    "sh_degree": KnobSpec(lambda base: (0, 1, 2, 3), "colour SH degree 0..3"),
    "components": KnobSpec(lambda base: ("3dgs", "csm", "csm+plm", "csm+plm+ggs", "auto"),
                           "NimbusGS components (3dgs: the 3DGS method)"),
}
_NAME = re.compile(r"^[a-z_][a-z0-9_]*$")


# --- the sweep ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class SweepPoint:
    """One (knob, value) of a sweep and the cell that measures it.

    Attributes
    ----------
    knob : str
        Config field swept (or ``components``).
    value : str
        The value as the sweep names it (``"150"``, ``"csm+plm"``, ``"3dgs"``).
    cell : Cell
    base : bool
        The cell is the base cell (the value is the base config's).
    """

    knob: str
    value: str
    cell: Cell
    base: bool


def parse_knobs(specs: Sequence[str] | None) -> list[tuple[str, tuple[str, ...] | None]]:
    """Parse ``--knob`` tokens: ``NAME`` (the default values) or ``NAME=V1,V2,...``.

    Returns
    -------
    list of (name, values or None)
        In the order given; None means "the knob's default values" (:data:`KNOBS`).

    Raises
    ------
    NimbusError
        A malformed token, a knob given twice, an empty value list, or a bare name
        without default values.
    """
    out: list[tuple[str, tuple[str, ...] | None]] = []
    for token in specs or []:
        name, sep, rest = token.partition("=")
        name = name.strip()
        if not _NAME.match(name):
            raise NimbusError(f"--knob {token!r}: expected NAME or NAME=V1,V2,... with NAME a config setting "
                              f"(e.g. iterations=150,300,600); knobs with defaults: {', '.join(KNOBS)}")
        if any(name == n for n, _ in out):
            raise NimbusError(f"--knob {name} is given twice; list all its values in one token ({name}=V1,V2,...)")
        if not sep:
            if name not in KNOBS:
                raise NimbusError(f"--knob {name} has no default values; give them ({name}=V1,V2,...) or use one "
                                  f"of {', '.join(KNOBS)}")
            out.append((name, None))
            continue
        values = tuple(dict.fromkeys(v.strip() for v in rest.split(",") if v.strip()))
        if not values:
            raise NimbusError(f"--knob {token!r} lists no values; give e.g. {name}=V1,V2")
        out.append((name, values))
    return out


def base_cell(scene: str = DEFAULT_SCENE, weather: str = DEFAULT_WEATHER, method: str = DEFAULT_METHOD,
              preset: str = DEFAULT_PRESET, seed: int = 0, size: str = DEFAULT_SIZE,
              overrides: dict[str, str] | None = None) -> Cell:
    """The sweep's base cell, validated like any grid cell (NimbusError on a bad name or override)."""
    from benchmark.grid import build_cells

    return build_cells([scene], [weather], [method], [preset], [seed], size, overrides)[0]


def build_sweep(base: Cell, knobs: Sequence[tuple[str, tuple[str, ...] | None]] | None = None) -> list[SweepPoint]:
    """The sweep's points: the base cell's one-knob variations, validated before anything runs.

    Parameters
    ----------
    base : Cell
        The base cell (its ``overrides`` are the base ``--set`` values).
    knobs : list of (name, values or None), optional
        :func:`parse_knobs` output.  None: every knob of :data:`KNOBS` that the base
        method's config has, with its default values.

    Raises
    ------
    NimbusError
        A knob the base method's config lacks, or a value its config rejects.
    """
    from benchmark.cell import make_config
    from nimbus.methods.registry import get_method

    method = get_method(base.method)
    base_ov = dict(base.overrides)
    base_config = make_config(method, base.preset, base_ov)
    if knobs is None:
        knobs = [(k, None) for k in KNOBS if hasattr(base_config, k)]
    points: list[SweepPoint] = []
    for name, values in knobs:
        if not hasattr(base_config, name):
            raise NimbusError(f"--knob {name}: the {base.method} method's config ({type(base_config).__name__}) has "
                              f"no setting {name!r}" + (" (a NimbusGS setting: use --method nimbus)"
                                                        if name in KNOBS else ""))
        if values is None:
            values = tuple(str(v) for v in KNOBS[name].defaults(getattr(base_config, name)))
        for value in values:
            cell = _variation(base, base_config, name, value)
            points.append(SweepPoint(name, value, cell, cell.cell_id == base.cell_id))
    return points


def _variation(base: Cell, base_config, name: str, value: str) -> Cell:
    from benchmark.cell import make_config
    from nimbus.methods.registry import get_method

    if name == "components" and value in METHOD_VALUES:
        method_name = METHOD_VALUES[value]
        fields = {f.name for f in dataclasses.fields(get_method(method_name).preset(base.preset))}
        ov = {k: v for k, v in base.overrides if k in fields}
        try:
            make_config(get_method(method_name), base.preset, ov)
        except NimbusError as e:
            raise NimbusError(f"--knob {name}={value}: {_without_set_prefix(e)}") from None
        return Cell(base.scene, base.weather, method_name, base.preset, base.seed, base.size,
                    tuple(sorted(ov.items())))
    setting = value.replace("+", ",") if name == "components" else value
    ov = {**dict(base.overrides), name: setting}
    try:
        config = make_config(get_method(base.method), base.preset, ov)
    except NimbusError as e:
        hint = "".join(f" (or {v}: the {m} method)" for v, m in METHOD_VALUES.items()) if name == "components" else ""
        raise NimbusError(f"--knob {name}={value}: {_without_set_prefix(e)}{hint}") from None
    if config == base_config:
        return base
    return Cell(base.scene, base.weather, base.method, base.preset, base.seed, base.size, tuple(sorted(ov.items())))


def _without_set_prefix(error: Exception) -> str:
    """The config's message without its ``--set KEY=VALUE:`` lead (the knob's own lead names the value)."""
    msg = str(error)
    if msg.startswith("--set ") and ": " in msg:
        return msg.split(": ", 1)[1]
    return msg


def sweep_cells(points: Sequence[SweepPoint]) -> list[Cell]:
    """The distinct cells of a sweep, in first-appearance order."""
    return list({p.cell.cell_id: p.cell for p in points}.values())


# --- Pareto fronts -------------------------------------------------------------------------------
def pareto_front(cost: Sequence[float | None], quality: Sequence[float | None],
                 higher_is_better: bool = True) -> np.ndarray:
    """Which points are non-dominated, for a cost to minimise and a quality to maximise (or minimise).

    Point j dominates point i when ``cost[j] <= cost[i]`` and ``quality[j]`` is at least as
    good as ``quality[i]``, one of the two strictly.  Identical points do not dominate each
    other (both are on the front).  A point with a missing (None or NaN) cost or quality
    is never on the front and dominates nothing.

    Parameters
    ----------
    cost : sequence of float, length N
        E.g. training time in seconds or peak memory in MB (lower is better).
    quality : sequence of float, length N
        E.g. PSNR (``higher_is_better=True``) or LPIPS (False).

    Returns
    -------
    ndarray of bool, shape (N,)
    """
    c = np.array([np.nan if v is None else float(v) for v in cost], dtype=np.float64)
    q = np.array([np.nan if v is None else float(v) for v in quality], dtype=np.float64)
    if c.shape != q.shape:
        raise ValueError(f"cost and quality differ in length ({c.size} vs {q.size})")
    if not higher_is_better:
        q = -q
    valid = np.isfinite(c) & np.isfinite(q)
    front = valid.copy()
    for i in np.flatnonzero(valid):
        dominated_by = valid & (c <= c[i]) & (q >= q[i]) & ((c < c[i]) | (q > q[i]))
        front[i] = not dominated_by.any()
    return front


# --- the table ----------------------------------------------------------------------------------------
def tradeoff_rows(points: Sequence[SweepPoint], records: dict[str, dict]) -> list[dict]:
    """One row per sweep point with its cell's metrics and costs and the four Pareto flags.

    Parameters
    ----------
    points : sequence of SweepPoint
    records : dict
        ``cell_id -> record`` (:meth:`benchmark.store.ResultsStore.latest`); a point whose
        cell has no ``ok`` record gets its status and empty metrics, and is on no front.

    Returns
    -------
    list of dict
        Keys :data:`CSV_COLUMNS`.  The fronts are computed over the distinct cells, so
        the base cell, listed under every knob, counts once, on values rounded to
        :data:`FRONT_DECIMALS`.
    """
    metrics = ("psnr", "ssim", "lpips", "train_time_s", "wall_time_s", "peak_memory_mb", "num_gaussians",
               "iterations")
    rows = []
    for p in points:
        rec = records.get(p.cell.cell_id, {})
        ok = rec.get("status") == "ok"
        row = {"knob": p.knob, "value": p.value, "base": p.base, "method": p.cell.method, "cell_id": p.cell.cell_id,
               "status": rec.get("status", "missing")}
        row.update({m: (_number(rec.get(m)) if ok else None) for m in metrics})
        rows.append(row)
    cells = list(dict.fromkeys(r["cell_id"] for r in rows))
    first = {cid: next(r for r in rows if r["cell_id"] == cid) for cid in cells}
    for (quality, cost), column in zip(PANELS, PARETO_COLUMNS):
        flags = pareto_front([_round(first[c][cost], FRONT_DECIMALS[cost]) for c in cells],
                             [_round(first[c][quality], FRONT_DECIMALS[quality]) for c in cells],
                             HIGHER_IS_BETTER[quality])
        on = {cid: bool(f) for cid, f in zip(cells, flags)}
        for r in rows:
            r[column] = on[r["cell_id"]]
    return rows


def _round(v, decimals: int):
    return None if v is None else round(float(v), decimals)


def _number(v):
    return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else v


#: What tradeoff.md shows: the knob is the row label; numbers as printed (never ranked: the fronts mark instead).
MD_COLUMNS = (
    Column("shown_value", "value", "value", align="left"), Column("shown_psnr", "PSNR↑", "PSNR", 2),
    Column("shown_ssim", "SSIM↑", "SSIM", 3), Column("shown_lpips", "LPIPS↓", "LPIPS", 3),
    Column("shown_train_time_s", "train s", "train s", 1), Column("shown_wall_time_s", "cell s", "cell s", 1),
    Column("shown_peak_memory_mb", "peak MB", "peak MB", 0),
    Column("shown_num_gaussians", "Gaussians", "Gaussians", 0),
    *(Column(f"front_{c}", f"front {q.upper()}/{COST_NAMES[k].replace('memory', 'mem')}",
             f"front {q.upper()}/{COST_NAMES[k]}", align="center")
      for (q, k), c in zip(PANELS, PARETO_COLUMNS)))
CSV_FORMAT = LongFormat("tradeoff.csv", "the trade-off sweep, one line per (knob, value)", CSV_COLUMNS)
#: Values shown rounded (``shown_<key>``); the CSV lines carry them raw, as the row's fields.
_SHOWN = ("psnr", "ssim", "lpips", "train_time_s", "wall_time_s", "peak_memory_mb", "num_gaussians")


def tradeoff_table(rows: Sequence[dict], title: str = "Trade-off", notes: Sequence[str] = ()) -> Table:
    """The sweep as a :class:`~benchmark.tables.model.Table`: one row per (knob, value), a ● in a front column
    for a cell on that panel's Pareto front; its CSV lines carry the rows' raw fields (:data:`CSV_COLUMNS`)."""
    out = []
    for r in rows:
        value = r["value"] + (" (base)" if r["base"] else "") + ("" if r["status"] == "ok" else f" [{r['status']}]")
        values = {("", "shown_value"): value, **{("", f"shown_{c}"): r[c] for c in _SHOWN},
                  **{("", f"front_{c}"): "●" if r[c] else "" for c in PARETO_COLUMNS}}
        out.append(Row(r["knob"], values, fields={c: "" if r[c] is None else r[c] for c in CSV_COLUMNS}))
    return Table("tradeoff", "tradeoff", title, MD_COLUMNS, [""], [Block(out, ranked=False)], lead=("knob",),
                 notes=[n.rstrip(".") for n in notes], group_heads=False, csv=CSV_FORMAT)


def to_csv(rows: Sequence[dict]) -> str:
    """CSV with :data:`CSV_COLUMNS`, values unrounded, missing values empty."""
    return writer.to_csv([tradeoff_table(rows)])


def to_markdown(rows: Sequence[dict], title: str = "Trade-off", notes: Sequence[str] = ()) -> str:
    """The table in GitHub Markdown (the table writer's)."""
    return writer.to_markdown(tradeoff_table(rows, title, notes))


# --- the plot ------------------------------------------------------------------------------------------
def plot_tradeoff(rows: Sequence[dict], title: str = "") -> bytes:
    """The 2 x 2 trade-off figure as PNG bytes (matplotlib's Agg canvas; no display, no pyplot state).

    Panels: PSNR and LPIPS (rows) against training time and peak memory (columns).  Each
    knob's cells are one colour, joined in the sweep's value order and labelled with
    their value; the base cell is a black star; the Pareto front is a dashed step line
    (the best quality reachable within a cost) through circled cells.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 9), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 2)
    ok = [r for r in rows if r["status"] == "ok"]
    knobs = list(dict.fromkeys(r["knob"] for r in rows))
    colours = {k: f"C{i % 10}" for i, k in enumerate(knobs)}
    for ax, (quality, cost), column in zip(axes.flat, PANELS, PARETO_COLUMNS):
        ax.set_xlabel(AXIS_LABELS[cost])
        ax.set_ylabel(AXIS_LABELS[quality])
        ax.set_title(f"{quality.upper()} vs {COST_NAMES[cost]}")
        have = [r for r in ok if r[quality] is not None and r[cost] is not None]
        if not have:
            ax.text(0.5, 0.5, f"{quality.upper()} not computed", ha="center", va="center", transform=ax.transAxes)
            continue
        for k in knobs:
            pts = [r for r in have if r["knob"] == k]
            if not pts:
                continue
            ax.plot([r[cost] for r in pts], [r[quality] for r in pts], "-o", color=colours[k], lw=0.8, ms=5,
                    alpha=0.85, label=k)
            for r in pts:
                if not r["base"]:
                    ax.annotate(r["value"], (r[cost], r[quality]), textcoords="offset points", xytext=(4, 3),
                                fontsize=7, color=colours[k])
        base = next((r for r in have if r["base"]), None)
        if base is not None:
            ax.plot([base[cost]], [base[quality]], "*", color="black", ms=13, zorder=5, label="base")
        front = sorted({r["cell_id"]: r for r in have if r[column]}.values(), key=lambda r: (r[cost], r[quality]))
        if front:
            xs, ys = [r[cost] for r in front], [r[quality] for r in front]
            ax.step(xs, ys, where="post", color="0.25", ls="--", lw=1.2, zorder=1, label="Pareto front")
            ax.scatter(xs, ys, s=150, facecolors="none", edgecolors="black", lw=1.1, zorder=6)
        ax.grid(alpha=0.3)
    handles, labels = [], []
    for ax in axes.flat:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    if handles:
        fig.legend(handles, labels, loc="outside right center", fontsize=9)
    if title:
        fig.suptitle(title)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    return buf.getvalue()


def write_tradeoff(rows: Sequence[dict], out: str | Path, title: str = "", header: Sequence[str] = ()) -> list[Path]:
    """Write ``tradeoff.csv``, ``.md`` and ``.png`` into ``out``; each is rendered first, then written atomically."""
    from nimbus.utils.fs import atomic_write_bytes, atomic_write_text

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise NimbusError(f"--out {out} is a file; give a folder")
    table = tradeoff_table(rows, title or "Trade-off", header)
    texts = {"tradeoff.csv": writer.to_csv([table]), "tradeoff.md": writer.to_markdown(table)}
    png = plot_tradeoff(rows, title)
    written = [atomic_write_text(out / name, text) for name, text in texts.items()]
    written.append(atomic_write_bytes(out / "tradeoff.png", png))
    return written
