"""The paper's ablation tables, ours from the results store and the paper's own numbers.

Layouts (``nimbusgs.tex``):

==========================  ==========================  ===============================================
file stem                   paper table                 rows x columns
==========================  ==========================  ===============================================
``ablation_components``     ``tab:ablation``            CSM (H) / PLM (R) / GGS (H+R+S) blocks x Average
``ablation_ggs``            ``tab:ablation_ggs``        GGS factors (H+R+S) x Average
``ablation_loss``           ``tab:ablation_loss``       loss terms (H+R+S) x Average
``ablation_minit``          ``tab:ablation_iteration``  M_init schedules (H+R+S) x scenes
==========================  ==========================  ===============================================

Which of our methods fills which paper row is the data in :data:`ABLATIONS` (method
names from :mod:`nimbus.methods.registry`); the paper's "Ours" is ``nimbus-full``
(:data:`~benchmark.tables.results.ABLATION_OURS`), the configuration every ablation variant
changes one thing of, and our row says so (``Ours (nimbus-full: csm+plm+ggs)``; the per-weather
tables' "Ours" is ``nimbus``, components by ``auto``).  Values are means over
the seeds of a cell; an ``Average`` is the mean over the scenes the block's rows were
run on, and is left empty (never zero) for a row that misses one of them.  A table is
written when the store has at least one of its variant rows (``Ours``, shared by the
tables, does not count); rows not run are shown as missing.  Best / second-best marks are
ranked within a block (the paper marks only the best, in bold, in these tables).

The paper's numbers are package data (``benchmark/data/paper/ablations/``) and are written
beside ours (``paper_<stem>``), labelled as the paper's numbers on the paper's data.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterator, Sequence

from benchmark.data import PAPER_ABLATIONS_DIR, read_csv
from benchmark.tables.model import AVERAGE, Block, LongFormat, Row, Table
from benchmark.tables.results import (ABLATION_OURS, METRIC_COLUMNS, METRICS, average, finished, ordered, protocols,
                                      scene_means)

if TYPE_CHECKING:  # importlib.resources.abc is Python 3.11+
    from importlib.resources.abc import Traversable

#: Our configuration behind the paper's "Ours" row of the ablations (every component forced on).
OURS = ABLATION_OURS.method
CSV = LongFormat("ablations.csv", "ablation tables, long format",
                 ("table", "paper_label", "preset", "block", "weather", "variant", "method", "scene", *METRICS,
                  *(f"{k}_mark" for k in METRICS), "runs", "ssim_protocol", "lpips_net"))
#: Plain-text row and column names typeset as the paper does (others are escaped).
LATEX_LABELS = {"M_init": r"$M_\text{init}$", "w/o L_DCP": r"w/o $\mathcal{L}_\text{DCP}$",
                "w/ L_DCP (stage 2)": r"w/ $\mathcal{L}_\text{DCP}$ (stage 2)",
                "w/o L_TV": r"w/o $\mathcal{L}_\text{TV}$"}
#: LaTeX packages of the ablation and runtime tables (``amsmath`` for :data:`LATEX_LABELS`).
LATEX_PACKAGES = "booktabs,multirow,graphicx,amsmath"


@dataclass(frozen=True)
class AblationRow:
    """One row of an ablation table.

    Attributes
    ----------
    label : str
        The paper's row name (plain text; ``benchmark/data/paper/ablations/*.csv`` uses it too).
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
        The paper's numbers: a file in ``benchmark/data/paper/ablations/``.
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


def by_preset(frame, key: str, title: str) -> Iterator[tuple[str, str, str, object]]:
    """(key, title, preset, records) per preset; the key names the preset only when there are several."""
    presets = ordered(frame["preset"])
    for p in presets:
        suffix = f"_{p}" if len(presets) > 1 else ""
        yield key + suffix, f"{title}, preset {p}", p, frame[frame["preset"] == p]


def _layout(spec: AblationSpec, blocks: list[Block], groups: list[str], **kw) -> Table:
    """A table of ``spec``'s layout (ours or the paper's)."""
    return Table(kw.pop("key", spec.key), spec.key, columns=METRIC_COLUMNS, groups=groups, blocks=blocks,
                 lead=(spec.first_column, "Type"), group_heads=spec.columns != "average",
                 latex_packages=LATEX_PACKAGES, latex_names=LATEX_LABELS, marks_scope=" (per block)", **kw)


def _block(b: AblationBlock, rows: list[Row], **kw) -> Block:
    return Block(rows, f"{b.name} ({b.weather})", {"block": b.name, "weather": b.weather}, **kw)


def _ablation_table(spec: AblationSpec, frame, key: str, title: str, preset: str, ssim_protocol: str,
                    lp: str) -> Table | None:
    blocks: list[Block] = []
    scenes: dict[int, list[str]] = {}
    notes: list[str] = []
    found = False
    for bi, block in enumerate(spec.blocks):
        sub = frame[(frame["weather"] == block.weather) & frame["method"].isin([r.method for r in block.rows])]
        cells = scene_means(sub, "method")
        scenes[bi] = ordered(sub["scene_label"])
        rows = []
        for ar in block.rows:
            have = [s for s in scenes[bi] if (ar.method, s) in cells]
            found |= bool(have) and ar.method != OURS  # "Ours" alone is no ablation
            row = Row(ABLATION_OURS.label if ar.method == OURS else ar.label, rule_before=ar.rule_before,
                      fields={"variant": ar.label, "method": ar.method,
                              "runs": sum(cells[(ar.method, s)][1] for s in have)})
            for s in have:
                row.values.update({(s, k): cells[(ar.method, s)][0][k] for k in METRICS})
            if spec.columns == "average":
                for k in METRICS:
                    row.values[(AVERAGE, k)] = average([row.values.get((s, k)) for s in scenes[bi]])
                if have and len(have) < len(scenes[bi]):
                    notes.append(f"{ar.label} ({ar.method}) was run on {len(have)} of the {len(scenes[bi])} "
                                 f"{block.weather} scenes, so it has no Average")
            rows.append(row)
        # An averaged table's CSV lists each scene too: the Average's inputs.
        blocks.append(_block(block, rows, csv_groups=(*scenes[bi], AVERAGE) if spec.columns == "average" else None))
    if not found:
        return None
    groups = [AVERAGE] if spec.columns == "average" else ordered(s for bi in scenes for s in scenes[bi])
    average_over = "; ".join(f"{b.name or b.weather}: {', '.join(scenes[bi]) or 'none run'}"
                             for bi, b in enumerate(spec.blocks))
    what = "Average = mean over the scenes" if spec.columns == "average" else "column groups = scenes"
    ours = f"; {ABLATION_OURS.note()}" if OURS in spec.methods else ""
    extra = [r.label for b in spec.blocks for r in b.rows if not r.in_paper]
    extra = f"; rows not in the paper's table: {', '.join(extra)}" if extra else ""
    notes.insert(0, f"SSIM protocol: {ssim_protocol}; LPIPS: {lp}; mean over seeds; {what} ({average_over})"
                    f"{ours}{extra}")
    return _layout(spec, blocks, groups, key=key, title=title, notes=notes,
                   label=f"tab:nimbus-bench-{key.replace('_', '-')}", what=f"ours: {title} (paper layout "
                   f"{spec.paper_label})", comment="rows -> methods: " + "; ".join(dict.fromkeys(
                       f"{r.label} = {r.method}" for b in spec.blocks for r in b.rows)),
                   csv=CSV, fields={"table": key, "paper_label": spec.paper_label, "preset": preset,
                                    "ssim_protocol": ssim_protocol, "lpips_net": lp})


def tables(df, method_order: Sequence[str] = ()) -> tuple[list[Table], list[str]]:
    """Our ablation tables (one per layout with a variant row in the store, one per preset when the store
    mixes presets), and ``"<stem> (<paper label>)"`` of each layout the store has no variant row of.

    ``method_order`` is unused: the rows are the paper's.
    """
    ok = finished(df)
    ssim_protocol, lp = protocols(ok)
    out: list[Table] = []
    skipped: list[str] = []
    for spec in ABLATIONS:
        relevant = ok[ok["method"].isin(spec.methods)]
        made = [t for key, title, preset, frame in by_preset(relevant, spec.key, spec.title)
                if (t := _ablation_table(spec, frame, key, title, preset, ssim_protocol, lp)) is not None]
        out += made
        if not made:
            skipped.append(f"{spec.key} ({spec.paper_label})")
    return out, skipped


def paper(folder: Traversable = PAPER_ABLATIONS_DIR) -> dict[str, Table]:
    """The paper's ablation tables by file stem (those whose reference file exists).

    The paper's numbers on the paper's (real) scenes, in our layout, labelled as such.
    """
    out: dict[str, Table] = {}
    for spec in ABLATIONS:
        path = folder / spec.reference
        if not path.is_file():
            continue
        records = read_csv(path)
        known = {r.label for b in spec.blocks for r in b.rows if r.in_paper}
        if {r["variant"] for r in records} != known:
            raise ValueError(f"{path}: its variants {sorted({r['variant'] for r in records})} are not the paper "
                             f"rows of {spec.key} {sorted(known)}")
        blocks, index = [], {}
        for b in spec.blocks:
            rows = [Row(r.label, rule_before=r.rule_before) for r in b.rows if r.in_paper]
            index.update({(b.weather, r.label): r for r in rows})
            blocks.append(_block(b, rows))
        for r in records:
            index[(r["weather"], r["variant"])].values.update({(r["scene"], k): float(r[k]) for k in METRICS})
        label = records[0]["table_label"]
        out[spec.key] = _layout(
            spec, blocks, list(dict.fromkeys(r["scene"] for r in records)), key=f"paper_{spec.key}",
            title=f"the paper's reported numbers on the paper's data ({label}: {spec.title})",
            label=f"tab:nimbus-bench-paper-{spec.key.replace('_', '-')}",
            notes=[f"Transcribed from nimbusgs.tex {label}; NOT results of this benchmark (other scenes); SSIM as "
                   "3DGS evaluates it, LPIPS VGG; the paper marks only the best (bold)"])
    return out
