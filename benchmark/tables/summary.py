"""The summary of a results store: one row per weather setting x method, means over its finished cells.

One :class:`~benchmark.tables.model.Table`, written by the one writer: as text at the end of ``nimbus-bench
run`` (:func:`summary_text`) and as the HTML report's sortable first table (:mod:`benchmark.html_report`).
Each weather setting is a block (best and second best marked per setting); a row's values are the means
of PSNR / SSIM / LPIPS / training seconds over its finished cells (every scene and seed), with its cell and
error counts.  With records that carry the degraded input's own score (:mod:`benchmark.tables.inputs`) an
``Input PSNR`` column gives each row the PSNR of its degraded test views themselves, what it has to beat.  With
clean-ceiling records (:mod:`benchmark.tables.ceiling`) the ceiling is the first block and a ``ΔPSNR vs clean``
column gives each row's gap to it.
"""

from __future__ import annotations

from typing import Sequence

from benchmark.cell import CEILING
from benchmark.tables import ceiling, inputs
from benchmark.tables.model import Block, Column, Row, Table
from benchmark.tables.results import METRIC_COLUMNS, finished, labelled, ordered, protocols
from nimbus.errors import NimbusError

#: Columns of the summary besides PSNR / SSIM / LPIPS.
TIME_COLUMN = Column("train_time_s", "Train s↓", "Train s", 1, higher_is_better=False)
COUNT_COLUMNS = (Column("cells", "Cells", "Cells"), Column("errors", "Errors", "Errors"))
SUMMARY_COLUMNS = (*METRIC_COLUMNS, TIME_COLUMN, *COUNT_COLUMNS)
#: The summary's gap to the clean ceiling, shown when the store has one.
GAP_COLUMN = Column("d_psnr_ceiling", "ΔPSNR vs clean", r"$\Delta$PSNR vs clean", 2)


def summary_table(df, method_order: Sequence[str] = (), strict: bool = True) -> Table:
    """Per weather setting (a block) x method (a row): means over the finished cells, counts, marks.

    ``strict``: raise NimbusError for a store without a finished cell or mixing protocols (the report);
    otherwise (what a run prints of its own cells) say so in a note.
    """
    from weather_synth.settings import family_order

    if strict:
        finished(df)
    every = labelled(df.copy())
    ok = every[every["status"] == "ok"]
    ceilings = ceiling.split(ok)[1]
    given = not inputs.carried(ok).empty
    blocks = []
    for w in ordered(every["weather"], (CEILING, *family_order())):
        sub = every[every["weather"] == w]
        rows = []
        for m in ordered(sub["method_label"], method_order):
            g = sub[sub["method_label"] == m]
            good = g[g["status"] == "ok"]
            row = Row(ceiling.label(m) if w == CEILING else m, fields={"method": m})
            for col in (*METRIC_COLUMNS, TIME_COLUMN):
                v = good[col.key].astype(float)
                row.values[("", col.key)] = None if len(v) == 0 or v.isna().any() else float(v.mean())
            row.values[("", "cells")] = float(len(g))
            row.values[("", "errors")] = float(len(g) - len(good))
            if given:
                row.values[("", inputs.COLUMN.key)] = inputs.row_value(good)
            if len(ceilings) and w != CEILING:
                row.values[("", GAP_COLUMN.key)] = ceiling.mean_gap(good, ceilings)
            rows.append(row)
        blocks.append(Block(rows, name=w, fields={"weather": w}))
    notes = []
    if len(ok):
        try:
            ssim_protocol, lp = protocols(ok)
            notes.append(f"Means over the finished cells of each setting (every scene and seed) against the clean "
                         f"test views; SSIM protocol: {ssim_protocol}; LPIPS: {lp}; Train s: the training loop's "
                         "wall-clock seconds. Best and second best marked per setting")
        except NimbusError as e:
            if strict:
                raise
            notes.append(f"Note: {e}")
    if given:
        notes.append(inputs.summary_note())
    if len(ceilings):
        notes.append(f"{CEILING} = the clean ceiling, {ceiling.LABEL}: 3dgs trained on the clean training views; "
                     f"{GAP_COLUMN.text} = the mean over a row's finished cells of the cell's PSNR minus its scene's "
                     "ceiling (same size and preset), dB")
    columns = (*SUMMARY_COLUMNS, *([inputs.COLUMN] if given else []), *([GAP_COLUMN] if len(ceilings) else []))
    return Table("summary", "summary", "Summary", columns, [""], blocks, lead=("Method", "Weather"), notes=notes)


def summary_text(df, method_order: Sequence[str] = ()) -> str:
    """The summary as the text ``nimbus-bench run`` prints (``(no results)`` for none)."""
    from benchmark.tables.writer import to_text

    if df is None or len(df) == 0:
        return "(no results)\n"
    return to_text(summary_table(df, method_order, strict=False))
