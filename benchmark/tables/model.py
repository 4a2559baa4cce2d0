"""The table model: a table layout as data (columns, column groups, blocks of rows, notes).

Every table ``nimbus-bench tables`` writes, ours and the paper's, is a :class:`Table` built by a
layout module (:mod:`~benchmark.tables.comparison`, :mod:`~benchmark.tables.ablation`,
:mod:`~benchmark.tables.runtime`) and rendered by the one writer, :mod:`benchmark.tables.writer`,
to LaTeX (booktabs), Markdown and long-format CSV.

Shape::

    Table
      columns   value columns (PSNR, SSIM, ...), repeated in every column group
      groups    column groups (scenes, "Average"), each a header spanning the columns
      blocks    rows compared with each other: best / second-best marks are ranked per block
        Block.rows   Row(label, values[(group, column key)] -> float or None)

Marks: within a block, for each (group, ranked column), the best value is marked when at
least two rows have a value and the second best when at least three do; values are compared
as printed (:func:`rank_marks`), so equal printed values share a mark.  A block that is not
:attr:`Block.ranked` (a reference row, differences) has no marks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

AVERAGE = "Average"


def finite(v) -> bool:
    """True for a number that is not None, NaN or infinite."""
    return v is not None and isinstance(v, (int, float)) and math.isfinite(v)


def rank_marks(values: Sequence[float | None], higher_better: bool, decimals: int) -> list[int | None]:
    """1 for the best value, 2 for the second best, None otherwise (values compared as printed).

    The best is marked when at least two values exist, the second best when at least three do.
    """
    present = [round(v, decimals) for v in values if finite(v)]
    if len(present) < 2:
        return [None] * len(values)
    order = sorted(set(present), reverse=higher_better)
    out: list[int | None] = []
    for v in values:
        if not finite(v):
            out.append(None)
            continue
        r = order.index(round(v, decimals)) + 1
        out.append(1 if r == 1 else 2 if r == 2 and len(present) >= 3 else None)
    return out


@dataclass(frozen=True)
class Column:
    """A value column: how it is headed, printed and ranked.

    Attributes
    ----------
    key : str
        Name of its values in :attr:`Row.values` and of its CSV column (``psnr``, ``params_M``).
    text, latex : str
        Its head in Markdown and in LaTeX.
    decimals : int
        Decimals printed (and compared at, for the marks).
    higher_is_better : bool or None
        Ranking direction; None: not ranked (no marks).
    unit : str
        Suffix of every printed value (``M`` in ``94.1M``).
    significant : int
        At least this many significant digits are printed (more decimals for small values);
        0: always :attr:`decimals`.
    align : {"right", "left", "center", "none"}
        Alignment of the Markdown column (LaTeX centres every value column, as the paper does).
    """

    key: str
    text: str
    latex: str
    decimals: int = 0
    higher_is_better: bool | None = None
    unit: str = ""
    significant: int = 0
    align: str = "right"

    @property
    def ranked(self) -> bool:
        return self.higher_is_better is not None

    def format(self, v: float | str | None, missing: str) -> str:
        """``v`` as printed (text as it is), or ``missing``."""
        if isinstance(v, str):
            return v
        if not finite(v):
            return missing
        decimals = self.decimals
        if self.significant and v != 0:
            decimals = max(decimals, self.significant - 1 - math.floor(math.log10(abs(v))))
        return f"{v:.{decimals}f}{self.unit}"


@dataclass
class Row:
    """One row: a label and its values.

    Attributes
    ----------
    label : str
        Plain text (LaTeX via :attr:`Table.latex_names`, else escaped).
    values : dict
        ``(group, column key) -> float, text or None``; a missing key is printed as missing.  Text
        is printed as it is and never ranked.
    rule_before : bool
        A rule above the row in LaTeX (the paper separates "Ours" from the variants so).
    fields : dict
        Long-format CSV fields of every line of the row (``method``, ``runs``).
    group_fields : dict
        ``group -> {CSV field: value}`` for the row's line of that group (``seeds``).
    """

    label: str
    values: dict[tuple[str, str], float | str | None] = field(default_factory=dict)
    rule_before: bool = False
    fields: dict[str, Any] = field(default_factory=dict)
    group_fields: dict[str, dict[str, Any]] = field(default_factory=dict)


@dataclass
class Block:
    """Rows ranked together.  With several blocks, a second label column shows each block's name.

    Attributes
    ----------
    rows : list of Row
    name : str
        Shown in the block column (``Hazy (H)``).
    fields : dict
        Long-format CSV fields of the block's lines (``block``, ``weather``).
    csv_groups : tuple of str or None
        Groups the long-format CSV lists for this block (an ``Average`` column's inputs, say);
        None: the table's groups; ``()``: none (rows derived from other blocks' values).
    ranked : bool
        Whether its rows get marks (False: a reference row or differences, never best or second).
    """

    rows: list[Row]
    name: str = ""
    fields: dict[str, Any] = field(default_factory=dict)
    csv_groups: tuple[str, ...] | None = None
    ranked: bool = True

    @property
    def labels(self) -> list[str]:
        return [r.label for r in self.rows]


@dataclass(frozen=True)
class LongFormat:
    """A CSV file of many tables, one line per (table, block, group, row).

    A line's fields come from the table's, the block's and the row's ``fields``, the row's
    ``group_fields`` of the group, the group itself (under :attr:`group_field`), each
    column's value (unrounded; empty when missing) and ``<key>_mark`` (``best`` / ``second``).
    """

    name: str
    what: str
    columns: tuple[str, ...]
    group_field: str = "scene"


@dataclass(frozen=True)
class Combined:
    """The Markdown file that gathers a set of layouts' tables (ours, each followed by the paper's)."""

    name: str
    what: str


@dataclass
class Table:
    """One table, ours or the paper's, ready to render.

    Attributes
    ----------
    key : str
        File stem (``weather_H``, ``paper_ablation_ggs``).
    layout : str
        Tables of one layout are listed together, the paper's after ours (``H``, ``ablation_ggs``).
    title : str
        Markdown heading; LaTeX caption after :attr:`caption_lead`.
    columns : tuple of Column
    groups : list of str
        Column groups, in order.
    blocks : list of Block
    lead : tuple of str
        Heads of the label columns: the row labels', then the block names' (several blocks only).
    notes : list of str
        Sentences under the table (protocols, what is missing and why).
    label : str
        LaTeX ``\\label``.
    what : str
        What ``nimbus-bench tables`` lists beside the files (default: the title).
    caption_lead : str
        Words before the title in the LaTeX caption.
    group_heads : bool
        Head each group (two header rows); False: one header row of the columns.
    wide : bool
        A ``table*`` across the page, one source line per column group.
    latex_packages : str
        The ``\\usepackage`` the LaTeX needs besides ``xcolor``.
    latex_names : dict
        Plain-text labels and heads typeset as LaTeX (``M_init`` -> ``$M_\\text{init}$``).
    comment : str or None
        One more sentence, in the LaTeX source and under the Markdown (the rows' methods).
    marks_scope : str
        Said after the Markdown's mark legend (`` (per block)``).
    csv : LongFormat or None
        The CSV file the table's lines go in (None: none).
    fields : dict
        Long-format CSV fields of all its lines.
    """

    key: str
    layout: str
    title: str
    columns: tuple[Column, ...]
    groups: list[str]
    blocks: list[Block]
    lead: tuple[str, ...] = ("Method",)
    notes: list[str] = field(default_factory=list)
    label: str = ""
    what: str = ""
    caption_lead: str = ""
    group_heads: bool = True
    wide: bool = False
    latex_packages: str = "booktabs,multirow,graphicx"
    latex_names: dict[str, str] = field(default_factory=dict)
    comment: str | None = None
    marks_scope: str = ""
    csv: LongFormat | None = None
    fields: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        if len(self.lead) < (2 if len(self.blocks) > 1 else 1):
            raise ValueError(f"table {self.key}: {len(self.blocks)} blocks need {min(len(self.blocks), 2)} lead "
                             f"heads (rows, blocks), got {self.lead}")

    @property
    def ranked(self) -> bool:
        return any(c.ranked for c in self.columns)

    def row(self, label: str, block: int = 0) -> Row:
        """The row labelled ``label`` in ``block``."""
        return next(r for r in self.blocks[block].rows if r.label == label)

    def marks(self, group: str, column: str, block: int = 0) -> list[int | None]:
        """Each row's mark (1 best, 2 second, None) in ``group``'s ``column`` within ``block``."""
        col = next(c for c in self.columns if c.key == column)
        values = [r.values.get((group, column)) for r in self.blocks[block].rows]
        if not col.ranked or not self.blocks[block].ranked:
            return [None] * len(values)
        return rank_marks(values, col.higher_is_better, col.decimals)
