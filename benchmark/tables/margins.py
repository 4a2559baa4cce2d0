"""Where NimbusGS wins and by how much: "Ours" against each other method, cell by cell (``margins``).

Layout: one table; a row per weather setting (another protocol family's settings after the
default's seven), then ``All`` (every scene and setting); a column group per other method in the
store.  In each group, over the scenes both methods have (means over seeds, as the per-weather
tables): ``ΔPSNR`` and ``ΔSSIM`` (Ours minus the other), ``ΔLPIPS`` (the other minus Ours), so
that a positive value is Ours better on all three, and ``won`` (scenes where Ours' PSNR is the
higher, of those both have; the CSV has ``won`` and ``scenes`` as numbers).  The per-weather tables hold the values; this one answers "where
does NimbusGS win, and where does a baseline" without subtracting by hand.  "Ours" is
:data:`~benchmark.tables.results.COMPARISON_OURS` (the method a user runs, components by ``auto``).
There is no paper counterpart (the paper's tables are other scenes).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from benchmark.tables.model import Block, Column, LongFormat, Row, Table, finite
from benchmark.tables.results import COMPARISON_OURS, METRICS, finished, ordered, protocols, scene_means

#: The signed differences (positive: Ours better) and the PSNR win count.
COLUMNS = (
    Column("d_psnr", "ΔPSNR", r"$\Delta$PSNR", 2),
    Column("d_ssim", "ΔSSIM", r"$\Delta$SSIM", 3),
    Column("d_lpips", "ΔLPIPS", r"$\Delta$LPIPS", 3),
    Column("wins", "won", "won", align="center"),
)
#: Sign of each metric's difference so that positive is Ours better.
SIGN = {"psnr": 1.0, "ssim": 1.0, "lpips": -1.0}
ALL = "All"
CSV = LongFormat("margins.csv", "Ours against each other method, per setting, long format",
                 ("weather", "other", "d_psnr", "d_ssim", "d_lpips", "won", "scenes", "ssim_protocol", "lpips_net"),
                 group_field="other")


def _margins(pairs: list[tuple[dict, dict]]) -> tuple[dict[str, float | str | None], dict[str, int]]:
    """The group's values and CSV fields for ``(ours, other)`` metric dicts of the scenes both have."""
    if not pairs:
        return {}, {}
    values: dict[str, float | str | None] = {}
    for k in METRICS:
        diffs = [SIGN[k] * (a[k] - b[k]) for a, b in pairs if finite(a[k]) and finite(b[k])]
        values[f"d_{k}"] = float(np.mean(diffs)) if len(diffs) == len(pairs) else None
    won = sum(1 for a, b in pairs if finite(a["psnr"]) and finite(b["psnr"]) and a["psnr"] > b["psnr"])
    values["wins"] = f"{won}/{len(pairs)}"
    return values, {"won": won, "scenes": len(pairs)}


def tables(df, method_order: Sequence[str] = ()) -> tuple[list[Table], list[str]]:
    """The margins table of the store's finished cells, or none (and why) without Ours or another method."""
    from weather_synth.settings import family_order

    ok = finished(df)
    ssim_protocol, lp = protocols(ok)
    ours_labels = ordered(ok.loc[ok["method"] == COMPARISON_OURS.method, "method_label"])
    if not ours_labels:
        return [], [f"margins (no {COMPARISON_OURS.method} cell to compare)"]
    ours = ours_labels[0]  # with several presets, the first (the others are compared as methods of their own)
    others = [m for m in ordered(ok["method_label"], method_order) if m != ours]
    if not others:
        return [], [f"margins (no method besides {ours} to compare with)"]
    means: dict[tuple[str, str, str], dict] = {}
    for weather, sub in ok.groupby("weather", sort=False):
        for (m, s), (vals, _) in scene_means(sub, "method_label").items():
            means[(weather, m, s)] = vals
    weathers = ordered(ok["weather"], family_order())

    def pairs(weather_set: list[str], other: str) -> list[tuple[dict, dict]]:
        return [(means[(w, ours, s)], means[(w, other, s)]) for (w, m, s) in means
                if w in weather_set and m == ours and (w, other, s) in means]

    rows = []
    for label in [*weathers, ALL]:
        row = Row(label, fields={"weather": label}, rule_before=label == ALL)
        for other in others:
            values, fields = _margins(pairs(weathers if label == ALL else [label], other))
            row.values.update({(other, k): v for k, v in values.items()})
            if fields:
                row.group_fields[other] = fields
        rows.append(row)
    title = f"{COMPARISON_OURS.label} against each other method"
    notes = [f"Over the scenes both methods have (means over seeds): ΔPSNR and ΔSSIM = Ours minus the other, ΔLPIPS "
             f"= the other minus Ours, so positive is Ours better; won = scenes where Ours' PSNR is the higher. "
             f"{ALL} = every scene and setting. SSIM protocol: {ssim_protocol}; LPIPS: {lp}; {COMPARISON_OURS.note()}"]
    return [Table("margins", "margins", title, columns=COLUMNS, groups=others, blocks=[Block(rows)],
                  lead=("Setting",), notes=notes, label="tab:nimbus-bench-margins", caption_lead="Margins: ",
                  wide=True, what=f"ours: {title}", csv=CSV,
                  fields={"ssim_protocol": ssim_protocol, "lpips_net": lp})], []


def paper() -> dict[str, Table]:
    """None: the paper's numbers are other scenes (its per-weather tables are beside ours)."""
    return {}
