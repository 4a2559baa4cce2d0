"""The paper's ablation tables and its complexity / runtime table from the results store.

Layouts (``nimbusgs.tex``):

==========================  ==========================  ===============================================
file stem                   paper table                 rows x columns
==========================  ==========================  ===============================================
``ablation_components``     ``tab:ablation``            CSM (H) / PLM (R) / GGS (H+R+S) blocks x Average
``ablation_ggs``            ``tab:ablation_ggs``        GGS factors (H+R+S) x Average
``ablation_loss``           ``tab:ablation_loss``       loss terms (H+R+S) x Average
``ablation_minit``          ``tab:ablation_iteration``  M_init schedules (H+R+S) x scenes
``runtime``                 ``tab:runtime``             methods (H+R+S) x Params. / Memory / Training / FPS
==========================  ==========================  ===============================================

Which of our methods fills which paper row is the data in :data:`ABLATIONS` (method
names from :mod:`nimbus.nimbusgs.methods`); the paper's "Ours" is ``nimbus-full``,
the configuration every ablation variant changes one thing of.  Values are means over
the seeds of a cell; an ``Average`` is the mean over the scenes the block's rows were
run on, and is left empty (never zero) for a row that misses one of them.  A table is
written when the store has at least one of its variant rows (``Ours``, shared by the
tables, does not count); rows not run are shown as missing.
Best / second-best marks follow :func:`benchmark.tables.rank_marks`, within a block
(the paper marks only the best, in bold, in these tables).

The paper's numbers are in ``tables/reference/ablations/`` and are written beside ours
(``paper_<stem>``), labelled as the paper's numbers on the paper's data.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from benchmark.tables import (
    AVERAGE, DECIMALS, HIGHER_IS_BETTER, LATEX_HEADS, LATEX_MACROS, MARK_MACROS, METRICS, MISSING_LATEX,
    MISSING_TEXT, PAPER_REFERENCE_DIR, TEXT_HEADS, Written, _finite, _labels, _ok_frame, _ordered, _protocols,
    latex_escape, rank_marks,
)

#: Our configuration behind the paper's "Ours" row of the ablations (every component forced on).
OURS = "nimbus-full"
ABLATION_REFERENCE_DIR = PAPER_REFERENCE_DIR / "ablations"
MARK_WORDS = {1: "best", 2: "second"}
#: Plain-text row and column names typeset as the paper does (others are escaped).
LATEX_LABELS = {"M_init": r"$M_\text{init}$", "w/o L_DCP": r"w/o $\mathcal{L}_\text{DCP}$",
                "w/ L_DCP (stage 2)": r"w/ $\mathcal{L}_\text{DCP}$ (stage 2)",
                "w/o L_TV": r"w/o $\mathcal{L}_\text{TV}$"}


@dataclass(frozen=True)
class AblationRow:
    """One row of an ablation table.

    Attributes
    ----------
    label : str
        The paper's row name (plain text; ``tables/reference/ablations/*.csv`` uses it too).
    method : str
        Our method (``nimbus-train --method``) whose results fill the row.
    in_paper : bool
        False for rows this project adds (the paper has no numbers for them).
    rule_before : bool
        A rule above the row, where the paper separates "Ours" from the variants.
    """

    label: str
    method: str
    in_paper: bool = True
    rule_before: bool = False


@dataclass(frozen=True)
class AblationBlock:
    """Rows compared with each other (marks are per block) on one weather setting.

    ``name`` is the paper's "Type" column (empty for a table of one block).
    """

    name: str
    weather: str
    rows: tuple[AblationRow, ...]


@dataclass(frozen=True)
class AblationSpec:
    """One ablation table's layout.

    Attributes
    ----------
    key : str
        File stem of the written table.
    title : str
        What the table compares.
    paper_label : str
        The paper's ``\\label``.
    columns : {"average", "scenes"}
        One ``Average`` column group, or the scenes as column groups (no average).
    blocks : tuple of AblationBlock
    reference : str
        The paper's numbers: a file in ``tables/reference/ablations/``.
    first_column : str
        Head of the row-label column.
    """

    key: str
    title: str
    paper_label: str
    columns: str
    blocks: tuple[AblationBlock, ...]
    reference: str
    first_column: str = "Variant"

    @property
    def methods(self) -> list[str]:
        return list(dict.fromkeys(r.method for b in self.blocks for r in b.rows))


def _ggs_or_loss(key, title, label, reference, variants) -> AblationSpec:
    rows = tuple(AblationRow(v, m) for v, m in variants) + (AblationRow("Ours", OURS, rule_before=True),)
    return AblationSpec(key, title, label, "average", (AblationBlock("", "H+R+S", rows),), reference)


#: Paper row -> our method, per ablation table, in the paper's order.
ABLATIONS: tuple[AblationSpec, ...] = (
    AblationSpec(
        "ablation_components", "Ablation of CSM (hazy), PLM (rainy) and GGS (hybrid)", "tab:ablation", "average", (
            AblationBlock("Hazy", "H", (
                AblationRow("Gaussian-Driven Extinction", "nimbus-gaussian-extinction"),
                AblationRow("Uniform Extinction", "nimbus-uniform-extinction"),
                AblationRow("w/o CSM", "nimbus-no-csm", in_paper=False),
                AblationRow("Ours", OURS))),
            AblationBlock("Rainy", "R", (
                AblationRow("Restored-Derived Residuals", "nimbus-restored-residuals"),
                AblationRow("w/o PLM", "nimbus-no-plm", in_paper=False),
                AblationRow("Ours", OURS))),
            AblationBlock("Hybrid", "H+R+S", (
                AblationRow("w/o GGS", "nimbus-no-ggs"),
                AblationRow("Ours", OURS))),
        ), "components.csv"),
    _ggs_or_loss("ablation_ggs", "Factor-wise ablation of GGS (H+R+S)", "tab:ablation_ggs", "ggs.csv", (
        ("w/o Depth", "nimbus-ggs-no-depth"), ("w/o Projected Radius", "nimbus-ggs-no-radius"),
        ("w/o Reconstruction Error", "nimbus-ggs-no-error"))),
    _ggs_or_loss("ablation_loss", "Ablation of loss terms (H+R+S)", "tab:ablation_loss", "loss.csv", (
        ("w/o L_DCP", "nimbus-no-dcp"), ("w/ L_DCP (stage 2)", "nimbus-dcp-stage2"), ("w/o L_TV", "nimbus-no-tv"))),
    AblationSpec(
        "ablation_minit", "Ablation of the geometry-initialisation length M_init (H+R+S)", "tab:ablation_iteration",
        "scenes", (AblationBlock("", "H+R+S", tuple(
            AblationRow(f"{k}K", f"nimbus-minit-{k}k") for k in (1, 2, 4, 10, 15))),),
        "minit.csv", first_column="M_init"),
)


@dataclass(frozen=True)
class RuntimeColumn:
    """One column of the complexity / runtime table: a store column shown in the paper's unit."""

    head: str
    store_column: str
    scale: float          # store unit -> shown unit
    unit: str             # suffix of each cell, as the paper prints it
    decimals: int         # the paper's; more where a small value needs them (two significant digits)
    reference_column: str  # column of ``runtime.csv``


RUNTIME_COLUMNS = (
    RuntimeColumn("Params.", "num_params", 1e-6, "M", 1, "params_M"),
    RuntimeColumn("Memory", "peak_memory_mb", 1 / 1024, "G", 1, "memory_G"),
    RuntimeColumn("Training", "train_time_s", 1 / 60, "min", 0, "training_min"),
    RuntimeColumn("FPS", "render_fps", 1.0, "", 0, "fps"),
)
RUNTIME_KEY, RUNTIME_LABEL, RUNTIME_WEATHER, RUNTIME_REFERENCE = "runtime", "tab:runtime", "H+R+S", "runtime.csv"
RUNTIME_TITLE = f"Model complexity and runtime ({RUNTIME_WEATHER})"
RUNTIME_NOTE = ("Params. = optimised parameter count; Memory = peak training memory (CUDA allocator peak on a GPU, "
                "process resident-set high-water mark on a CPU); Training = wall-clock training time; FPS = "
                "test-view rendering speed")
PAPER_RUNTIME_NOTE = ("Params., Memory, Training and FPS denote parameter count, training memory usage, training time "
                      "and rendering speed (the paper's caption)")


# --- tables ------------------------------------------------------------------------------------
@dataclass
class AblationTable:
    """One ablation table, ours or the paper's.

    Attributes
    ----------
    spec : AblationSpec
    blocks : list of AblationBlock
        The spec's blocks (the paper's table keeps only its own rows).
    groups : list of str
        Column groups: ``["Average"]`` or scene names.
    values : dict
        ``(block index, row label, group, metric) -> float or None``.
    runs : dict
        ``(block index, row label) -> number of records averaged``.
    scenes : dict
        ``block index -> scenes`` the block's rows were run on.
    """

    spec: AblationSpec
    blocks: list[AblationBlock]
    groups: list[str]
    values: dict[tuple[int, str, str, str], float | None]
    runs: dict[tuple[int, str], int] = field(default_factory=dict)
    scenes: dict[int, list[str]] = field(default_factory=dict)
    preset: str | None = None
    key: str = ""
    caption: str = ""
    notes: list[str] = field(default_factory=list)
    paper: bool = False
    ssim_protocol: str = "3dgs"
    lpips: str = "lpips-vgg-v0.1"

    def marks(self, block: int, group: str, metric: str) -> list[int | None]:
        rows = self.blocks[block].rows
        return rank_marks([self.values.get((block, r.label, group, metric)) for r in rows],
                          HIGHER_IS_BETTER[metric], DECIMALS[metric])


@dataclass
class RuntimeTable:
    """The complexity / runtime table: ``values[(method, column head)]`` in the paper's units."""

    methods: list[str]
    values: dict[tuple[str, str], float | None]
    runs: dict[str, int] = field(default_factory=dict)
    scenes: list[str] = field(default_factory=list)
    preset: str | None = None
    key: str = RUNTIME_KEY
    caption: str = ""
    notes: list[str] = field(default_factory=list)
    paper: bool = False


# --- from the store ----------------------------------------------------------------------------
def _by_preset(frame, key: str, title: str):
    """(key, title, preset, records) per preset; the key names the preset only when there are several."""
    presets = _ordered(frame["preset"])
    for p in presets:
        suffix = f"_{p}" if len(presets) > 1 else ""
        yield key + suffix, f"{title}, preset {p}", p, frame[frame["preset"] == p]


def _scene_means(sub) -> dict[tuple[str, str], tuple[dict[str, float | None], int]]:
    """(method, scene) -> (metric -> mean over seeds, or None where a seed lacks it; number of records)."""
    out = {}
    for (m, s), g in sub.groupby(["method", "scene_label"], sort=False):
        means = {k: float(g[k].astype(float).mean()) if g[k].notna().all() else None for k in METRICS}
        out[(m, s)] = (means, len(g))
    return out


def _ablation_table(spec: AblationSpec, frame, key: str, title: str, preset: str) -> AblationTable | None:
    values: dict = {}
    runs: dict = {}
    scenes: dict = {}
    notes: list[str] = []
    found = False
    for bi, block in enumerate(spec.blocks):
        sub = frame[(frame["weather"] == block.weather) & frame["method"].isin([r.method for r in block.rows])]
        cells = _scene_means(sub)
        scenes[bi] = _ordered(sub["scene_label"])
        for row in block.rows:
            have = [s for s in scenes[bi] if (row.method, s) in cells]
            found |= bool(have) and row.method != OURS  # "Ours" alone is no ablation
            runs[(bi, row.label)] = sum(cells[(row.method, s)][1] for s in have)
            for s in have:
                for k in METRICS:
                    values[(bi, row.label, s, k)] = cells[(row.method, s)][0][k]
            if spec.columns == "average":
                for k in METRICS:
                    per = [values[(bi, row.label, s, k)] for s in have]
                    complete = len(have) == len(scenes[bi]) and all(_finite(v) for v in per)
                    values[(bi, row.label, AVERAGE, k)] = float(np.mean(per)) if have and complete else None
                if have and len(have) < len(scenes[bi]):
                    notes.append(f"{row.label} ({row.method}) was run on {len(have)} of the {len(scenes[bi])} "
                                 f"{block.weather} scenes, so it has no Average")
    if not found:
        return None
    groups = [AVERAGE] if spec.columns == "average" else _ordered(s for bi in scenes for s in scenes[bi])
    return AblationTable(spec, list(spec.blocks), groups, values, runs, scenes, preset, key, title, notes)


def _runtime_table(frame, key: str, title: str, preset: str, method_order: Sequence[str]) -> RuntimeTable:
    scenes = _ordered(frame["scene_label"])
    methods = _ordered(frame["method"], method_order)
    values: dict = {}
    runs: dict = {}
    notes: list[str] = []
    for m in methods:
        g = frame[frame["method"] == m]
        runs[m] = len(g)
        have = _ordered(g["scene_label"])
        for col in RUNTIME_COLUMNS:
            per_scene = [g[g["scene_label"] == s][col.store_column].astype(float) for s in have]
            complete = len(have) == len(scenes) and all(v.notna().all() for v in per_scene)
            values[(m, col.head)] = float(np.mean([v.mean() for v in per_scene])) * col.scale if complete else None
        if len(have) < len(scenes):
            notes.append(f"{m} was run on {len(have)} of the {len(scenes)} scenes, so it has no values")
    devices = sorted({str(r.get("device")) for r in frame["record"] if isinstance(r, dict) and r.get("device")})
    if len(devices) > 1:
        notes.append(f"the runs come from several devices ({', '.join(devices)}): their timings are not comparable")
    device = ", ".join(devices) if devices else "not recorded"
    notes.insert(0, f"{RUNTIME_NOTE}; device: {device}; mean over seeds, then over the scenes "
                    f"({', '.join(scenes)})")
    return RuntimeTable(methods, values, runs, scenes, preset, key, title, notes)


def ablation_tables(df, method_order: Sequence[str] = ()) -> tuple[list[AblationTable | RuntimeTable], list[str]]:
    """Our ablation tables and runtime table from the store, and the layouts not written (no variant run).

    Parameters
    ----------
    df : pandas.DataFrame
        :func:`benchmark.store.load_results` output.
    method_order : sequence of str
        Runtime-table methods listed first, in this order.

    Returns
    -------
    tables : list
        :class:`AblationTable` per layout with at least one row in the store (one per preset
        when the store mixes presets), then the :class:`RuntimeTable` (if the store has
        finished H+R+S cells).
    skipped : list of str
        ``"<stem> (<paper label>)"`` of each layout the store has no variant row of.
    """
    ok = _labels(_ok_frame(df))
    ssim_protocol, lp = _protocols(ok)
    tables: list = []
    skipped: list[str] = []
    for spec in ABLATIONS:
        relevant = ok[ok["method"].isin(spec.methods)]
        made = [t for key, title, preset, frame in _by_preset(relevant, spec.key, spec.title)
                if (t := _ablation_table(spec, frame, key, title, preset)) is not None]
        for t in made:
            t.ssim_protocol, t.lpips = ssim_protocol, lp
            average = "; ".join(f"{b.name or b.weather}: {', '.join(t.scenes[bi]) or 'none run'}"
                                for bi, b in enumerate(t.blocks))
            what = "Average = mean over the scenes" if spec.columns == "average" else "column groups = scenes"
            ours = f"; 'Ours' is {OURS} (every component on)" if OURS in spec.methods else ""
            extra = [r.label for b in spec.blocks for r in b.rows if not r.in_paper]
            extra = f"; rows not in the paper's table: {', '.join(extra)}" if extra else ""
            t.notes.insert(0, f"SSIM protocol: {ssim_protocol}; LPIPS: {lp}; mean over seeds; {what} ({average})"
                              f"{ours}{extra}")
        tables += made
        if not made:
            skipped.append(f"{spec.key} ({spec.paper_label})")
    hybrid = ok[ok["weather"] == RUNTIME_WEATHER]
    runtime = [_runtime_table(frame, key, title, preset, method_order)
               for key, title, preset, frame in _by_preset(hybrid, RUNTIME_KEY, RUNTIME_TITLE)]
    if not runtime:
        skipped.append(f"{RUNTIME_KEY} ({RUNTIME_LABEL})")
    return tables + runtime, skipped


# --- the paper's numbers -------------------------------------------------------------------------
def _read_csv(path: Path) -> list[dict]:
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


def paper_ablation_tables(folder: str | Path = ABLATION_REFERENCE_DIR) -> dict[str, AblationTable | RuntimeTable]:
    """The paper's ablation and runtime tables by file stem (those whose reference file exists).

    The paper's numbers on the paper's (real) scenes, in our layout, labelled as such.
    """
    folder = Path(folder)
    out: dict = {}
    for spec in ABLATIONS:
        path = folder / spec.reference
        if not path.is_file():
            continue
        rows = _read_csv(path)
        known = {r.label for b in spec.blocks for r in b.rows if r.in_paper}
        if {r["variant"] for r in rows} != known:
            raise ValueError(f"{path}: its variants {sorted({r['variant'] for r in rows})} are not the paper rows "
                             f"of {spec.key} {sorted(known)}")
        blocks = [AblationBlock(b.name, b.weather, tuple(r for r in b.rows if r.in_paper)) for b in spec.blocks]
        index = {(b.weather, r.label): bi for bi, b in enumerate(blocks) for r in b.rows}
        values = {(index[(r["weather"], r["variant"])], r["variant"], r["scene"], k): float(r[k])
                  for r in rows for k in METRICS}
        groups = list(dict.fromkeys(r["scene"] for r in rows))
        label = rows[0]["table_label"]
        out[spec.key] = AblationTable(
            spec, blocks, groups, values, key=spec.key, paper=True,
            caption=f"the paper's reported numbers on the paper's data ({label}: {spec.title})",
            notes=[f"Transcribed from nimbusgs.tex {label}; NOT results of this benchmark (other scenes); SSIM as "
                   "3DGS evaluates it, LPIPS VGG; the paper marks only the best (bold)"])
    path = folder / RUNTIME_REFERENCE
    if path.is_file():
        rows = _read_csv(path)
        label = rows[0]["table_label"]
        out[RUNTIME_KEY] = RuntimeTable(
            [r["method"] for r in rows],
            {(r["method"], c.head): float(r[c.reference_column]) for r in rows for c in RUNTIME_COLUMNS},
            key=RUNTIME_KEY, paper=True,
            caption=f"the paper's reported numbers on the paper's data ({label}: {RUNTIME_TITLE})",
            notes=[f"Transcribed from nimbusgs.tex {label}; NOT results of this benchmark (other scenes, the "
                   f"paper's GPU); {PAPER_RUNTIME_NOTE}"])
    return out


# --- formats -------------------------------------------------------------------------------------
def _metric_text(v: float | None, metric: str, missing: str) -> str:
    return missing if not _finite(v) else f"{v:.{DECIMALS[metric]}f}"


def runtime_text(v: float | None, col: RuntimeColumn, missing: str) -> str:
    """A runtime cell as the paper prints it (``94.1M``), with two significant digits at least."""
    if not _finite(v):
        return missing
    decimals = col.decimals if v == 0 else max(col.decimals, 1 - math.floor(math.log10(abs(v))))
    return f"{v:.{decimals}f}{col.unit}"


def _tex(text: str) -> str:
    return LATEX_LABELS.get(text) or latex_escape(text)


def _label_line(t) -> str:
    return rf"\label{{tab:nimbus-bench-{'paper-' if t.paper else ''}{t.key.replace('_', '-')}}}"


def _caption(t, marked: bool) -> str:
    marks = (r" The \colorbox{red!25}{best} and \colorbox{orange!25}{second-best} scores are colour-encoded."
             if marked else "")
    notes = " ".join(f"{latex_escape(n)}." for n in t.notes)
    return rf"\caption{{{latex_escape(t.caption)}.{marks} {notes}}}"


def _latex_open(spec_cols: str, t, mapping: str | None) -> list[str]:
    head = ["% Generated by `nimbus-bench tables`; needs \\usepackage{booktabs,multirow,graphicx,amsmath} and "
            "\\usepackage[table]{xcolor}."]
    if mapping:
        head.append(f"% rows -> methods: {mapping}")
    return head + [LATEX_MACROS, r"\begin{table}[!t]", r"\centering", r"\resizebox{\linewidth}{!}{%",
                   rf"\begin{{tabular}}{{{spec_cols}}}", r"\toprule"]


def _mapping(t: AblationTable) -> str | None:
    if t.paper:
        return None
    pairs = dict.fromkeys(f"{r.label} = {r.method}" for b in t.blocks for r in b.rows)
    return "; ".join(pairs)


def ablation_latex(t: AblationTable) -> str:
    """booktabs table in the paper's ablation layout (``Type`` column when there are several blocks)."""
    n = len(METRICS)
    multi = len(t.blocks) > 1
    lead = 2 if multi else 1
    ncols = lead + n * len(t.groups)
    lead_heads = [_tex(t.spec.first_column)] + (["Type"] if multi else [])
    lines = _latex_open("l" + (" c" if multi else "") + " " + " ".join("c" * n for _ in t.groups), t, _mapping(t))
    if t.groups == [AVERAGE]:
        lines.append(" & ".join(lead_heads + [LATEX_HEADS[k] for k in METRICS]) + r" \\")
    else:
        lines += [
            " & ".join([rf"\multirow{{2}}{{*}}{{{h}}}" for h in lead_heads]
                       + [rf"\multicolumn{{{n}}}{{c}}{{{latex_escape(g.capitalize())}}}" for g in t.groups]) + r" \\",
            "".join(rf"\cmidrule(lr){{{lead + 1 + n * i}-{lead + n * (i + 1)}}}" for i in range(len(t.groups))),
            " & ".join([""] * lead + [LATEX_HEADS[k] for _ in t.groups for k in METRICS]) + r" \\",
        ]
    lines.append(r"\midrule")
    for bi, block in enumerate(t.blocks):
        if bi:
            lines.append(rf"\cmidrule(lr){{1-{ncols}}}")
        marks = {(g, k): t.marks(bi, g, k) for g in t.groups for k in METRICS}
        for ri, row in enumerate(block.rows):
            if row.rule_before:
                lines.append(r"\midrule")
            cells = [_tex(row.label)]
            if multi:
                name = latex_escape(f"{block.name} ({block.weather})")
                cells.append(rf"\multirow{{{len(block.rows)}}}{{*}}{{{name}}}" if ri == 0 else "")
            for g in t.groups:
                for k in METRICS:
                    text = _metric_text(t.values.get((bi, row.label, g, k)), k, MISSING_LATEX)
                    mark = marks[(g, k)][ri]
                    cells.append(f"{MARK_MACROS[mark]}{{{text}}}" if mark else text)
            lines.append(" & ".join(cells) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}}", _caption(t, True), _label_line(t), r"\end{table}"]
    return "\n".join(lines) + "\n"


def _md_cell(text: str, mark: int | None) -> str:
    return f"**{text}**" if mark == 1 else f"_{text}_" if mark == 2 else text


def ablation_markdown(t: AblationTable) -> str:
    """GitHub Markdown: best **bold**, second best _italic_; the notes and the row -> method map below."""
    multi = len(t.blocks) > 1
    metric_heads = ([TEXT_HEADS[k] for k in METRICS] if t.groups == [AVERAGE]
                    else [f"{g} {TEXT_HEADS[k]}" for g in t.groups for k in METRICS])
    head = [t.spec.first_column] + (["Type"] if multi else []) + metric_heads
    lines = [f"### {t.caption}", "", "| " + " | ".join(head) + " |",
             "|" + "|".join([":---"] * (2 if multi else 1) + ["---:"] * len(metric_heads)) + "|"]
    for bi, block in enumerate(t.blocks):
        marks = {(g, k): t.marks(bi, g, k) for g in t.groups for k in METRICS}
        for ri, row in enumerate(block.rows):
            cells = [row.label] + ([f"{block.name} ({block.weather})"] if multi else [])
            cells += [_md_cell(_metric_text(t.values.get((bi, row.label, g, k)), k, MISSING_TEXT), marks[(g, k)][ri])
                      for g in t.groups for k in METRICS]
            lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    lines += ["", " ".join(f"{n}." for n in t.notes) + " Best **bold**, second best _italic_ (per block)."]
    mapping = _mapping(t)
    if mapping:
        lines.append(f"Rows -> methods: {mapping}.")
    return "\n".join(lines) + "\n"


def runtime_latex(t: RuntimeTable) -> str:
    """booktabs table in the paper's complexity / runtime layout (no marks, as in the paper)."""
    lines = _latex_open("l " + " ".join("c" for _ in RUNTIME_COLUMNS), t, None)
    lines += [" & ".join(["Method"] + [c.head for c in RUNTIME_COLUMNS]) + r" \\", r"\midrule"]
    for m in t.methods:
        cells = [latex_escape(m)] + [runtime_text(t.values.get((m, c.head)), c, MISSING_LATEX) for c in RUNTIME_COLUMNS]
        lines.append(" & ".join(cells) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}}", _caption(t, False), _label_line(t), r"\end{table}"]
    return "\n".join(lines) + "\n"


def runtime_markdown(t: RuntimeTable) -> str:
    head = ["Method"] + [c.head for c in RUNTIME_COLUMNS]
    lines = [f"### {t.caption}", "", "| " + " | ".join(head) + " |",
             "|" + "|".join([":---"] + ["---:"] * len(RUNTIME_COLUMNS)) + "|"]
    for m in t.methods:
        cells = [m] + [runtime_text(t.values.get((m, c.head)), c, MISSING_TEXT) for c in RUNTIME_COLUMNS]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    lines += ["", " ".join(f"{n}." for n in t.notes)]
    return "\n".join(lines) + "\n"


def to_latex(t: AblationTable | RuntimeTable) -> str:
    return runtime_latex(t) if isinstance(t, RuntimeTable) else ablation_latex(t)


def to_markdown(t: AblationTable | RuntimeTable) -> str:
    return runtime_markdown(t) if isinstance(t, RuntimeTable) else ablation_markdown(t)


def _num(v) -> str:
    return "" if not _finite(v) else repr(float(v))


def ablations_csv(tables: Sequence[AblationTable]) -> str:
    """Long format: one row per (table, block, row, scene or Average), values unrounded, marks as words.

    Averaged tables list each scene's values too (the Average's inputs).
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["table", "paper_label", "preset", "block", "weather", "variant", "method", "scene", *METRICS,
                *(f"{k}_mark" for k in METRICS), "runs", "ssim_protocol", "lpips_net"])
    for t in tables:
        for bi, block in enumerate(t.blocks):
            groups = [*t.scenes.get(bi, []), AVERAGE] if t.groups == [AVERAGE] else t.groups
            for g in groups:
                marks = {k: t.marks(bi, g, k) for k in METRICS}
                for ri, row in enumerate(block.rows):
                    w.writerow([t.key, t.spec.paper_label, t.preset, block.name, block.weather, row.label, row.method,
                                g, *(_num(t.values.get((bi, row.label, g, k))) for k in METRICS),
                                *(MARK_WORDS.get(marks[k][ri], "") for k in METRICS), t.runs.get((bi, row.label), 0),
                                t.ssim_protocol, t.lpips])
    return buf.getvalue()


def runtime_csv(tables: Sequence[RuntimeTable]) -> str:
    """One row per (table, method), in the paper's units (the reference file's columns), unrounded."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["table", "weather", "preset", "method", *(c.reference_column for c in RUNTIME_COLUMNS), "runs",
                "scenes"])
    for t in tables:
        for m in t.methods:
            w.writerow([t.key, RUNTIME_WEATHER, t.preset, m,
                        *(_num(t.values.get((m, c.head))) for c in RUNTIME_COLUMNS), t.runs.get(m, 0),
                        " ".join(t.scenes)])
    return buf.getvalue()


def write_ablation_tables(tables: Sequence[AblationTable | RuntimeTable], out: str | Path,
                          paper_reference: str | Path | None = ABLATION_REFERENCE_DIR) -> list[Written]:
    """Write ``<stem>.tex`` / ``.md`` per table, ``ablations.md`` (all), ``ablations.csv`` and ``runtime.csv``.

    Where the paper has the layout (``paper_reference``), ``paper_<stem>.tex`` / ``.md`` hold
    its numbers and the combined Markdown shows them after ours.
    """
    from nimbus.utils.fs import atomic_write_text

    out = Path(out)
    paper = paper_ablation_tables(paper_reference) if paper_reference is not None else {}
    written: list[Written] = []
    sections: list[str] = []
    by_layout: dict[str, list] = {}
    for t in tables:
        by_layout.setdefault(_layout(t), []).append(t)
    for layout, ours in by_layout.items():
        for t in ours:
            what = f"ours: {t.caption} (paper layout {_paper_label(t)})"
            written += [Written(atomic_write_text(out / f"{t.key}.tex", to_latex(t)), what),
                        Written(atomic_write_text(out / f"{t.key}.md", to_markdown(t)), what)]
            sections.append(to_markdown(t))
        ref = paper.get(layout)
        if ref is not None:
            written += [Written(atomic_write_text(out / f"paper_{layout}.tex", to_latex(ref)), ref.caption),
                        Written(atomic_write_text(out / f"paper_{layout}.md", to_markdown(ref)), ref.caption)]
            sections.append(to_markdown(ref))
    if sections:
        written.append(Written(atomic_write_text(out / "ablations.md", "\n".join(sections)),
                               "all ablation and runtime tables (ours, then the paper's)"))
    ablations = [t for t in tables if isinstance(t, AblationTable)]
    runtimes = [t for t in tables if isinstance(t, RuntimeTable)]
    if ablations:
        written.append(Written(atomic_write_text(out / "ablations.csv", ablations_csv(ablations)),
                               "ablation tables, long format"))
    if runtimes:
        written.append(Written(atomic_write_text(out / "runtime.csv", runtime_csv(runtimes)),
                               "complexity / runtime, one row per method"))
    return written


def _layout(t: AblationTable | RuntimeTable) -> str:
    return RUNTIME_KEY if isinstance(t, RuntimeTable) else t.spec.key


def _paper_label(t: AblationTable | RuntimeTable) -> str:
    return RUNTIME_LABEL if isinstance(t, RuntimeTable) else t.spec.paper_label
