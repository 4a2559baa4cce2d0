"""The clean ceiling in the tables: 3DGS trained on the clean views, and each method's gap to it.

A clean-ceiling cell (setting :data:`benchmark.cell.CEILING`, ``clean``) trains 3DGS on a scene's
clean training views with the weather cells' size, preset, seed and split, and is scored against
the same clean test views.  What a method scores below it is what the weather costs that method.

Every per-weather table (:mod:`.comparison`) shows, when the store has ceiling records for its
scenes, two more blocks under its methods: the ceiling row :data:`LABEL` (per scene, mean over its
seeds; ``Average`` over the table's scenes) and each method's gap to it, the method's value minus the
ceiling's for PSNR (dB), SSIM and LPIPS alike, computed from the values the table shows.  Neither block is ranked:
the ceiling is no competitor, and the gaps order the methods as their own values do.  The margins
table (:mod:`.margins`) adds the ceiling as one more column group, the summaries a ``ΔPSNR`` column.
A method row is compared with the ceiling of its own preset (and size, through the scene label).
A store without ceiling records gives none of this and says nothing about it.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from benchmark.cell import CEILING, CEILING_METHOD
from benchmark.tables.model import AVERAGE, Block, Row, finite
from benchmark.tables.results import METRICS, average, ordered, scene_means

#: The ceiling's row label (the method trained, and on what).
LABEL = "3DGS (clean views)"
#: Names of the blocks in a per-weather table with a ceiling.
CEILING_BLOCK = "clean ceiling"
GAP_BLOCK = "gap to ceiling"


def split(ok):
    """(the weather cells, the clean-ceiling cells) of a frame of records."""
    is_ceiling = ok["weather"] == CEILING
    return ok[~is_ceiling], ok[is_ceiling]


def label(method_label: str) -> str:
    """The row label of a ceiling record labelled ``method_label``: ``3dgs (fast)`` -> ``3DGS (clean views) (fast)``."""
    return LABEL + method_label[len(CEILING_METHOD):]


def preset_means(ceilings) -> dict[tuple[str, str], tuple[dict[str, float | None], int]]:
    """(preset, scene label) -> (metric -> mean over the ceiling's seeds, number of records)."""
    return scene_means(ceilings, "preset")


def blocks(rows: Sequence[Row], presets: dict[str, str], ceilings, scenes: Sequence[str]) -> list[Block]:
    """The ceiling block and the gap block of a per-weather table, or none without a ceiling for its rows.

    Parameters
    ----------
    rows : sequence of Row
        The table's method rows (values by ``(scene, metric)`` and ``(Average, metric)``; ``fields["method"]``
        the method label).
    presets : dict
        Method label -> its preset.
    ceilings : DataFrame
        The store's finished ceiling records (:func:`split`), labelled (:func:`~.results.labelled`).
    scenes : sequence of str
        The table's scene labels (its column groups besides ``Average``).
    """
    if len(ceilings) == 0:
        return []
    means = preset_means(ceilings)
    labels = {p: label(g["method_label"].iloc[0]) for p, g in ceilings.groupby("preset", sort=False)}
    wanted = [p for p in ordered(presets[r.fields["method"]] for r in rows)
              if p in labels and any((p, s) in means for s in scenes)]
    if not wanted:
        return []
    ceiling_rows = {}
    for p in wanted:
        row = Row(labels[p], fields={"method": labels[p]})
        for s in scenes:
            if (p, s) in means:
                row.values.update({(s, k): means[(p, s)][0][k] for k in METRICS})
                row.group_fields[s] = {"seeds": means[(p, s)][1]}
        for k in METRICS:
            row.values[(AVERAGE, k)] = average([row.values.get((s, k)) for s in scenes])
        ceiling_rows[p] = row
    gaps = []
    for r in rows:
        ceiling = ceiling_rows.get(presets[r.fields["method"]])
        if ceiling is None:
            continue
        gap = Row(r.label, fields={"method": r.fields["method"]})
        for s in scenes:
            gap.values.update({(s, k): _difference(r.values.get((s, k)), ceiling.values.get((s, k)))
                               for k in METRICS})
        for k in METRICS:
            gap.values[(AVERAGE, k)] = average([gap.values[(s, k)] for s in scenes])
        gaps.append(gap)
    # The gaps are derived from the lines above them: the long-format CSV keeps the measured values only.
    return [Block(list(ceiling_rows.values()), CEILING_BLOCK, ranked=False),
            Block(gaps, GAP_BLOCK, ranked=False, csv_groups=())]


def note() -> str:
    """What a table with the ceiling blocks says about them."""
    return (f"{LABEL} = the clean ceiling: {CEILING_METHOD} trained on the scene's clean training views (same views, "
            f"split, preset and seeds as the cells above; mean over its seeds); {GAP_BLOCK} = each method's value "
            "minus the ceiling's, per scene and in the Average (PSNR in dB; below zero in PSNR and SSIM, above zero in "
            "LPIPS: what the weather costs); neither block is ranked")


def cell_gaps(frame, ceilings, metric: str = "psnr"):
    """Each record's ``metric`` minus its ceiling's (same scene, size and preset; mean over the ceiling's seeds).

    A pandas Series aligned with ``frame``; NaN where the scene has no ceiling or a value is missing.
    """
    import pandas as pd

    ref = {key: float(g[metric].astype(float).mean()) if g[metric].notna().all() else np.nan
           for key, g in ceilings.groupby(["scene", "size", "preset"], sort=False)}
    return pd.Series([float(v) - ref.get((sc, sz, p), np.nan) if v is not None else np.nan
                      for v, sc, sz, p in zip(frame[metric], frame["scene"], frame["size"], frame["preset"])],
                     index=frame.index, dtype=float)


def mean_gap(frame, ceilings, metric: str = "psnr") -> float | None:
    """Mean over ``frame``'s records of :func:`cell_gaps`; None when there are none or one lacks a gap."""
    g = cell_gaps(frame, ceilings, metric)
    return float(g.mean()) if len(g) and g.notna().all() else None


def _difference(a, b) -> float | None:
    return float(a - b) if finite(a) and finite(b) else None
