"""The degraded input in the tables: the test views as the weather left them, scored like a method's renders.

A weather cell's record holds the input's own score (``input_psnr`` / ``input_ssim`` / ``input_lpips``,
:func:`benchmark.cell.score_input`): the setting's degraded test views (``images/``) against the same clean test
views, with the same scorer, views, SSIM protocol and LPIPS network as the cell's renders.  It is what a
reconstruction has to beat to be worth more than the degraded photo itself.

Every per-weather table (:mod:`.comparison`) whose records carry it shows one more block under its methods: the
row :data:`LABEL`, per scene the mean over the records that carry it (one value, whatever their method and seed),
``Average`` over the table's scenes (empty when a scene lacks it).  The block is not ranked: the input is no
competitor.  The run's summary (:mod:`.summary`) gives each row the :data:`COLUMN` ``Input PSNR``.  A store whose
records lack the fields (written before them) shows none of this and says nothing about it.
"""

from __future__ import annotations

from typing import Sequence

from benchmark.cell import INPUT_FIELDS
from benchmark.tables.model import AVERAGE, Block, Column, Row
from benchmark.tables.results import METRICS, average

#: The input's row label in the per-weather tables, and the name of its block.
LABEL = "degraded input (test views)"
BLOCK = "no reconstruction"
#: The summary's column of the input's PSNR.
COLUMN = Column(INPUT_FIELDS["psnr"], "Input PSNR", "Input PSNR", 2)


def carried(frame, metric: str = "psnr"):
    """The non-missing input values of ``metric`` in a frame of records, as floats (none in a store without them)."""
    import pandas as pd

    field = INPUT_FIELDS[metric]
    return frame[field].dropna().astype(float) if field in frame else pd.Series(dtype=float)


def blocks(frame, scenes: Sequence[str]) -> list[Block]:
    """The input block of a per-weather table, or none when no record of it carries the input's score.

    Parameters
    ----------
    frame : DataFrame
        The table's finished weather records, labelled (:func:`~.results.labelled`: ``scene_label``).
    scenes : sequence of str
        The table's scene labels (its column groups besides ``Average``).
    """
    if carried(frame).empty:
        return []
    row = Row(LABEL, fields={"method": LABEL})
    for s in scenes:
        here = frame[frame["scene_label"] == s]
        for k in METRICS:
            values = carried(here, k)
            row.values[(s, k)] = float(values.mean()) if len(values) else None
    for k in METRICS:
        row.values[(AVERAGE, k)] = average([row.values[(s, k)] for s in scenes])
    return [Block([row], BLOCK, ranked=False)]


def note() -> str:
    """What a table with the input block says about it."""
    return (f"{LABEL} = the setting's degraded test views themselves (images/, no reconstruction) scored against the "
            "clean test views with the same views and protocols as the methods (one value per scene, whatever the "
            "method and seed); not ranked: what a method has to beat")


def row_value(cells) -> float | None:
    """:data:`COLUMN` of a summary row: the mean input PSNR over the row's finished cells, None unless each has one."""
    values = carried(cells)
    return float(values.mean()) if len(values) and len(values) == len(cells) else None


def summary_note() -> str:
    """What the summary says about :data:`COLUMN`."""
    return (f"{COLUMN.text} = the degraded test views' own PSNR against the clean ones (no reconstruction; mean over "
            "a row's finished cells, n/a unless each has it): a row below it did worse than its input")
