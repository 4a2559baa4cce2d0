"""The paper's per-weather comparison tables from the results store, as LaTeX, Markdown and CSV.

Layout (``nimbusgs.tex``, tables ``tab:dehaze`` / ``tab:derain`` / ``tab:desnow`` / ``tab:mix`` and the
supplementary ``tab:h+r`` / ``tab:h+s`` / ``tab:r+s``):
one table per weather setting, methods as rows, scenes as column groups plus an
``Average`` group, each group PSNR↑ / SSIM↑ / LPIPS↓.  Values are means over the
seeds of a cell; ``Average`` is the mean over scenes and is left empty for a method
missing a scene.  The best value of a column is marked ``\\first`` (``\\cellcolor{red!25}``)
and the second best ``\\second`` (``\\cellcolor{orange!25}``), as the paper's macros
do; ranks compare the values as printed (ties share a mark), the best is marked
when at least two methods have a value and the second best when at least three do.
Every table states its SSIM protocol and LPIPS network.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

from nimbus.errors import NimbusError

METRICS = ("psnr", "ssim", "lpips")
HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "lpips": False}
DECIMALS = {"psnr": 2, "ssim": 3, "lpips": 3}  # as printed in the paper
LATEX_HEADS = {"psnr": r"PSNR$\uparrow$", "ssim": r"SSIM$\uparrow$", "lpips": r"LPIPS$\downarrow$"}
TEXT_HEADS = {"psnr": "PSNR↑", "ssim": "SSIM↑", "lpips": "LPIPS↓"}
AVERAGE = "Average"
#: The paper's colour macros (``nimbusgs.tex`` preamble); ``\providecommand`` keeps a document's own.
LATEX_MACROS = (r"\providecommand{\first}[1]{\cellcolor{red!25}{#1}}" "\n"
                r"\providecommand{\second}[1]{\cellcolor{orange!25}{#1}}")
MARK_MACROS = {1: r"\first", 2: r"\second"}
MISSING_TEXT = "–"
MISSING_LATEX = "--"


class Written(NamedTuple):
    """A file ``nimbus-bench tables`` wrote, and which table it holds."""

    path: Path
    what: str


@dataclass
class ComparisonTable:
    """One weather setting's method comparison.

    Attributes
    ----------
    weather : str
        Setting name (``H``, ``H+R``, ...).
    scenes : list of str
        Column groups, in order (``Average`` appended by the writers).
    methods : list of str
        Rows, in order.
    values : dict
        ``(method, scene or "Average", metric) -> float or None``.
    seeds : dict
        ``(method, scene) -> number of seeds averaged``.
    ssim_protocol, lpips : str
        What the SSIM and LPIPS columns are (stated in every format).
    """

    weather: str
    scenes: list[str]
    methods: list[str]
    values: dict[tuple[str, str, str], float | None]
    seeds: dict[tuple[str, str], int] = field(default_factory=dict)
    ssim_protocol: str = "3dgs"
    lpips: str = "lpips-vgg-v0.1"
    title: str | None = None   # default: the weather setting's description
    note: str | None = None    # default: :attr:`protocol_line`

    @property
    def groups(self) -> list[str]:
        return [*self.scenes, AVERAGE]

    def column(self, group: str, metric: str) -> list[float | None]:
        return [self.values.get((m, group, metric)) for m in self.methods]

    def marks(self, group: str, metric: str) -> list[int | None]:
        return rank_marks(self.column(group, metric), HIGHER_IS_BETTER[metric], DECIMALS[metric])

    @property
    def caption(self) -> str:
        return self.title or weather_caption(self.weather)

    @property
    def protocol_line(self) -> str:
        if self.note:
            return self.note
        return f"SSIM protocol: {self.ssim_protocol}; LPIPS: {self.lpips}; mean over seeds, Average = mean over scenes"


def rank_marks(values: Sequence[float | None], higher_better: bool, decimals: int) -> list[int | None]:
    """1 for the best value, 2 for the second best, None otherwise (values compared as printed).

    The best is marked when at least two values exist, the second best when at least three do.
    """
    present = [round(v, decimals) for v in values if _finite(v)]
    if len(present) < 2:
        return [None] * len(values)
    order = sorted(set(present), reverse=higher_better)
    out: list[int | None] = []
    for v in values:
        if not _finite(v):
            out.append(None)
            continue
        r = order.index(round(v, decimals)) + 1
        out.append(1 if r == 1 else 2 if r == 2 and len(present) >= 3 else None)
    return out


def _finite(v) -> bool:
    return v is not None and isinstance(v, (int, float)) and math.isfinite(v)


# --- from the store ----------------------------------------------------------------------------
def _ok_frame(df):
    if df is None or len(df) == 0:
        raise NimbusError("the results store is empty; run `nimbus-bench run` first")
    ok = df[df["status"] == "ok"].copy()
    if len(ok) == 0:
        raise NimbusError("the results store has no finished cell (every record is an error); see `error` in "
                          "results.jsonl and rerun `nimbus-bench run`")
    return ok


def _labels(ok):
    """Scene and method labels: the size / preset appear only when the store mixes several."""
    multi_size = ok["size"].nunique() > 1
    multi_preset = ok["preset"].nunique() > 1
    ok["scene_label"] = ok["scene"] + (("-" + ok["size"]) if multi_size else "")
    ok["method_label"] = ok["method"] + ((" (" + ok["preset"] + ")") if multi_preset else "")
    return ok


def _protocols(ok) -> tuple[str, str]:
    ssim = sorted(set(ok["ssim_protocol"].dropna()))
    if len(ssim) > 1:
        raise NimbusError(f"the store mixes SSIM protocols ({', '.join(ssim)}); one table needs one protocol: "
                          "rerun the cells with one --ssim (or use a separate --root)")
    nets = sorted(set(ok["lpips_net"].dropna()))
    if len(nets) > 1:
        raise NimbusError(f"the store mixes LPIPS networks ({', '.join(nets)}); rerun with one --lpips")
    if not nets:
        lp = "not computed"
    elif ok["lpips"].isna().any():
        lp = (f"lpips-{nets[0]}-v0.1, missing for some cells (weights not set up: run "
              "`nimbus-bench setup-weights`, then rerun those cells with --rerun)")
    else:
        lp = f"lpips-{nets[0]}-v0.1"
    return (ssim[0] if ssim else "3dgs"), lp


def _ordered(values, preferred: Sequence[str] = ()) -> list[str]:
    seen = list(dict.fromkeys(values))
    return [p for p in preferred if p in seen] + [v for v in seen if v not in preferred]


def comparison_tables(df, method_order: Sequence[str] = ()) -> list[ComparisonTable]:
    """One :class:`ComparisonTable` per weather setting of the store's finished cells.

    Parameters
    ----------
    df : pandas.DataFrame
        :func:`benchmark.store.load_results` output.
    method_order : sequence of str
        Methods listed first, in this order (others follow in store order).
    """
    from weather_synth.settings import ALL_SETTING_NAMES

    ok = _labels(_ok_frame(df))
    ssim_protocol, lp = _protocols(ok)
    tables = []
    for weather in _ordered(ok["weather"], ALL_SETTING_NAMES):
        sub = ok[ok["weather"] == weather]
        scenes = _ordered(sub["scene_label"])
        methods = _ordered(sub["method_label"], method_order)
        values: dict = {}
        seeds: dict = {}
        for (m, s), g in sub.groupby(["method_label", "scene_label"], sort=False):
            seeds[(m, s)] = len(g)
            for k in METRICS:
                col = g[k].astype(float)
                values[(m, s, k)] = float(col.mean()) if col.notna().all() else None
        for m in methods:
            for k in METRICS:
                per = [values.get((m, s, k)) for s in scenes]
                values[(m, AVERAGE, k)] = float(np.mean(per)) if all(_finite(v) for v in per) else None
        tables.append(ComparisonTable(weather, scenes, methods, values, seeds, ssim_protocol, lp))
    return tables


# --- formats -------------------------------------------------------------------------------------
def _fmt(v: float | None, metric: str, missing: str) -> str:
    return missing if not _finite(v) else f"{v:.{DECIMALS[metric]}f}"


_LATEX_SPECIAL = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
                  "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\^{}"}


def latex_escape(text: str) -> str:
    """``text`` with LaTeX's special characters escaped."""
    return "".join(_LATEX_SPECIAL.get(c, c) for c in text)


def weather_caption(weather: str) -> str:
    from weather_synth.settings import parse_setting

    return f"{parse_setting(weather).description} ({weather})"


def to_latex(t: ComparisonTable) -> str:
    """booktabs table in the paper's layout (needs ``booktabs``, ``multirow``, ``xcolor`` with ``table``)."""
    groups = t.groups
    n = len(METRICS)
    spec = "l " + " ".join("c" * n for _ in groups)
    lines = [
        "% Generated by `nimbus-bench tables`; needs \\usepackage{booktabs,multirow,graphicx} and "
        "\\usepackage[table]{xcolor}.",
        LATEX_MACROS,
        r"\begin{table*}[!t]",
        r"\centering",
        r"\setlength{\tabcolsep}{3.6pt}",
        r"\resizebox{\textwidth}{!}{%",
        rf"\begin{{tabular}}{{{spec}}}",
        r"\toprule",
        r"\multirow{2}{*}{Method} &" + " &".join(
            f"\n\\multicolumn{{{n}}}{{c}}{{{latex_escape(g.capitalize() if g != AVERAGE else g)}}}"
            for g in groups) + r" \\",
        "".join(rf"\cmidrule(lr){{{2 + n * i}-{1 + n * (i + 1)}}}" for i in range(len(groups))),
        "".join(f"& {' & '.join(LATEX_HEADS[k] for k in METRICS)}\n" for _ in groups).rstrip("\n") + r" \\",
        r"\midrule",
    ]
    marks = {(g, k): t.marks(g, k) for g in groups for k in METRICS}
    for i, m in enumerate(t.methods):
        row = [latex_escape(m)]
        for g in groups:
            cells = []
            for k in METRICS:
                text = _fmt(t.values.get((m, g, k)), k, MISSING_LATEX)
                mark = marks[(g, k)][i]
                cells.append(f"{MARK_MACROS[mark]}{{{text}}}" if mark else text)
            row.append(" & ".join(cells))
        lines.append("\n& ".join(row) + r" \\")
    lines += [
        r"\bottomrule",
        r"\end{tabular}}",
        rf"\caption{{Quantitative comparison: {latex_escape(t.caption)}. "
        r"The \colorbox{red!25}{best} and \colorbox{orange!25}{second-best} scores are colour-encoded. "
        rf"{latex_escape(t.protocol_line)}.}}",
        rf"\label{{tab:nimbus-bench-{'paper-' if t.note else ''}{t.weather.replace('+', '-')}}}",
        r"\end{table*}",
    ]
    return "\n".join(lines) + "\n"


def to_markdown(t: ComparisonTable) -> str:
    """GitHub Markdown: best **bold**, second best _italic_; the protocols under the table."""
    groups = t.groups
    head = ["Method"] + [f"{g} {TEXT_HEADS[k]}" for g in groups for k in METRICS]
    lines = [f"### {t.caption}", "",
             "| " + " | ".join(head) + " |",
             "|" + "|".join([":---"] + ["---:"] * (len(head) - 1)) + "|"]
    marks = {(g, k): t.marks(g, k) for g in groups for k in METRICS}
    for i, m in enumerate(t.methods):
        row = [m.replace("|", "\\|")]
        for g in groups:
            for k in METRICS:
                text = _fmt(t.values.get((m, g, k)), k, MISSING_TEXT)
                mark = marks[(g, k)][i]
                row.append(f"**{text}**" if mark == 1 else f"_{text}_" if mark == 2 else text)
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", f"{t.protocol_line}. Best **bold**, second best _italic_.", ""]
    return "\n".join(lines)


def to_csv(tables: Sequence[ComparisonTable]) -> str:
    """Long format: one row per (weather, method, scene or Average), values unrounded, marks as ranks."""
    import csv

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["weather", "method", "scene", *METRICS, *(f"{k}_mark" for k in METRICS), "seeds",
                "ssim_protocol", "lpips_net"])
    for t in tables:
        for g in t.groups:
            marks = {k: t.marks(g, k) for k in METRICS}
            for i, m in enumerate(t.methods):
                vals = [t.values.get((m, g, k)) for k in METRICS]
                w.writerow([t.weather, m, g, *("" if not _finite(v) else repr(float(v)) for v in vals),
                            *({1: "best", 2: "second"}.get(marks[k][i], "") for k in METRICS),
                            t.seeds.get((m, g), ""), t.ssim_protocol, t.lpips])
    return buf.getvalue()


#: The paper's reported numbers (package data, transcribed from ``nimbusgs.tex``); the ablation and
#: runtime tables' are in its ``ablations/`` folder (:mod:`benchmark.ablation_tables`).
from benchmark.data import PAPER_DIR as PAPER_REFERENCE_DIR  # noqa: E402


def paper_tables(folder: str | Path = PAPER_REFERENCE_DIR) -> dict[str, ComparisonTable]:
    """The paper's per-weather tables by weather setting (empty when the folder is absent).

    These are the paper's numbers on the paper's (real) scenes, labelled as such; they
    share the layout of ours, not the data.
    """
    import csv

    out: dict[str, ComparisonTable] = {}
    for f in sorted(Path(folder).glob("*.csv")) if Path(folder).is_dir() else []:
        with f.open(newline="") as fh:
            rows = list(csv.DictReader(fh))
        if not rows:
            continue
        label, weather = rows[0]["table_label"], rows[0]["weather"]
        values = {(r["method"], r["scene"], k): float(r[k]) for r in rows for k in METRICS}
        scenes = [s for s in dict.fromkeys(r["scene"] for r in rows) if s != AVERAGE]
        out[weather] = ComparisonTable(
            weather, scenes, list(dict.fromkeys(r["method"] for r in rows)), values,
            title=f"the paper's reported numbers on the paper's data ({label}, {weather_caption(weather)})",
            note=f"Transcribed from nimbusgs.tex {label}; NOT results of this benchmark (other scenes); "
                 "SSIM as 3DGS evaluates it, LPIPS VGG")
    return out


def write_tables(df, out: str | Path, method_order: Sequence[str] = (),
                 paper_reference: str | Path | None = PAPER_REFERENCE_DIR) -> list[Written]:
    """Write ``weather_<W>.tex`` / ``.md`` per setting, ``comparisons.md`` (all) and ``comparisons.csv``.

    Where the paper has a table for the same setting (``paper_reference``), ``comparisons.md``
    shows it after ours and ``paper_<W>.tex`` / ``.md`` hold it, labelled as the paper's numbers.
    """
    from nimbus.utils.fs import atomic_write_text

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise NimbusError(f"--out {out} is a file; give a folder")
    tables = comparison_tables(df, method_order)
    paper = paper_tables(paper_reference) if paper_reference is not None else {}
    written: list[Written] = []
    sections = []
    for t in tables:
        stem = f"weather_{t.weather}"
        what = f"ours: method comparison, {t.caption}"
        written.append(Written(atomic_write_text(out / f"{stem}.tex", to_latex(t)), what))
        written.append(Written(atomic_write_text(out / f"{stem}.md", to_markdown(t)), what))
        sections.append(to_markdown(t))
        if t.weather in paper:
            ref = paper[t.weather]
            written.append(Written(atomic_write_text(out / f"paper_{t.weather}.tex", to_latex(ref)), ref.caption))
            written.append(Written(atomic_write_text(out / f"paper_{t.weather}.md", to_markdown(ref)), ref.caption))
            sections.append(to_markdown(ref))
    written.append(Written(atomic_write_text(out / "comparisons.md", "\n".join(sections)),
                           "all method comparisons (ours, then the paper's)"))
    written.append(Written(atomic_write_text(out / "comparisons.csv", to_csv(tables)),
                           "all method comparisons, long format"))
    return written


# --- the end-of-run summary -------------------------------------------------------------------------
def summary_table(df, method_order: Sequence[str] = ()) -> str:
    """Plain-text table: mean per weather setting x method over scenes and seeds, with train time.

    Error cells are counted, not averaged.
    """
    from weather_synth.settings import ALL_SETTING_NAMES

    if df is None or len(df) == 0:
        return "(no results)"
    lines = [f"{'weather':<7} {'method':<16} {'cells':>5} {'PSNR':>7} {'SSIM':>6} {'LPIPS':>6} {'train s':>8} "
             f"{'errors':>6}"]
    for w in _ordered(df["weather"], ALL_SETTING_NAMES):
        sub = df[df["weather"] == w]
        for m in _ordered(sub["method"], method_order):
            g = sub[sub["method"] == m]
            ok = g[g["status"] == "ok"]

            def mean(col: str, spec: str) -> str:
                v = ok[col].astype(float)
                return "n/a" if len(v) == 0 or v.isna().any() else format(v.mean(), spec)

            lines.append(f"{w:<7} {m:<16} {len(g):>5} {mean('psnr', '7.2f'):>7} {mean('ssim', '6.3f'):>6} "
                         f"{mean('lpips', '6.3f'):>6} {mean('train_time_s', '8.1f'):>8} {len(g) - len(ok):>6}")
    ok = df[df["status"] == "ok"]
    if len(ok):
        try:
            ssim_protocol, lp = _protocols(ok.copy())
            lines.append(f"PSNR/SSIM/LPIPS against the clean test views; SSIM protocol: {ssim_protocol}; "
                         f"LPIPS: {lp}")
        except NimbusError as e:
            lines.append(f"note: {e}")
    return "\n".join(lines)
