"""Where NimbusGS wins and by how much: "Ours" against each other method, cell by cell (``margins``).

Layout: one table; a row per weather setting (another protocol family's settings after the
default's seven), then ``All`` (every scene and setting); a column group per other method in the
store.  In each group, over the scenes both methods have (means over seeds, as the per-weather
tables): ``ΔPSNR`` and ``ΔSSIM`` (Ours minus the other), ``ΔLPIPS`` (the other minus Ours), so
that a positive value is Ours better on all three, and ``won`` (scenes where Ours' PSNR is the
higher, of those both have; the CSV has ``won`` and ``scenes`` as numbers).  When the store holds two or
more training seeds of both methods on every scene of a row, ``±seed`` is the sample standard deviation,
over those seeds, of the row's ΔPSNR computed seed by seed: how far the margin moves with nothing but
the training seed, so a one-seed margin inside it is not a finding (the mean over n seeds moves by about
``±seed / sqrt(n)``; the CSV has ``seeds``).  At tiny size one seed's PSNR moves by 0.1 to 0.5 dB.  The
column is there only when some row has it.  The per-weather tables hold the values; this one answers
"where does NimbusGS win, and where does a baseline" without subtracting by hand.  "Ours" is
:data:`~benchmark.tables.results.COMPARISON_OURS` (the method a user runs, components by ``auto``).
When the store has clean-ceiling records (:mod:`benchmark.tables.ceiling`), the ceiling (3DGS trained
on the clean views, of Ours' preset) is one more group, last: Ours' gap to it in the same signs (below zero:
what the weather costs Ours), and ``won`` the scenes where Ours scores above it.
There is no paper counterpart (the paper's tables are other scenes).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from benchmark.cell import CEILING_METHOD
from benchmark.tables import ceiling
from benchmark.tables.model import Block, Column, LongFormat, Row, Table, finite
from benchmark.tables.provenance import mixed_note
from benchmark.tables.results import COMPARISON_OURS, METRICS, finished, ordered, protocols, scene_means

#: The signed differences (positive: Ours better) and the PSNR win count.
COLUMNS = (
    Column("d_psnr", "ΔPSNR", r"$\Delta$PSNR", 2),
    Column("d_ssim", "ΔSSIM", r"$\Delta$SSIM", 3),
    Column("d_lpips", "ΔLPIPS", r"$\Delta$LPIPS", 3),
    Column("wins", "won", "won", align="center"),
)
#: The seed spread of ΔPSNR, shown when some row has two or more seeds of both methods.
SEED_SD = Column("d_psnr_seed_sd", "±seed", r"$\pm$seed", 2)
#: Sign of each metric's difference so that positive is Ours better.
SIGN = {"psnr": 1.0, "ssim": 1.0, "lpips": -1.0}
ALL = "All"
CSV = LongFormat("margins.csv", "Ours against each other method, per setting, long format",
                 ("weather", "other", "d_psnr", "d_ssim", "d_lpips", "won", "scenes", "d_psnr_seed_sd", "seeds",
                  "ssim_protocol", "lpips_net"),
                 group_field="other")


def _seed_spread(pairs: list[tuple[dict, dict]]) -> tuple[float | None, int]:
    """Sample sd over the seeds both have in every pair of the per-seed mean PSNR margin, and that seed count.

    ``pairs`` holds ``(ours, other)`` maps ``seed -> PSNR`` (one per scene and setting); None below two seeds.
    """
    common = set.intersection(*(set(a) & set(b) for a, b in pairs)) if pairs else set()
    if len(common) < 2:
        return None, len(common)
    per_seed = [np.mean([a[k] - b[k] for a, b in pairs]) for k in sorted(common)]
    return float(np.std(per_seed, ddof=1)), len(common)


def _margins(pairs: list[tuple[dict, dict]]) -> tuple[dict[str, float | str | None], dict[str, int]]:
    """The group's values and CSV fields for ``(ours, other)`` metric dicts of the scenes both have.

    Each dict also holds ``seeds``: ``seed -> PSNR`` of the cell's finished seeds.
    """
    if not pairs:
        return {}, {}
    values: dict[str, float | str | None] = {}
    for k in METRICS:
        diffs = [SIGN[k] * (a[k] - b[k]) for a, b in pairs if finite(a[k]) and finite(b[k])]
        values[f"d_{k}"] = float(np.mean(diffs)) if len(diffs) == len(pairs) else None
    won = sum(1 for a, b in pairs if finite(a["psnr"]) and finite(b["psnr"]) and a["psnr"] > b["psnr"])
    values["wins"] = f"{won}/{len(pairs)}"
    sd, seeds = _seed_spread([(a["seeds"], b["seeds"]) for a, b in pairs])
    values[SEED_SD.key] = sd
    return values, {"won": won, "scenes": len(pairs), "seeds": seeds}


def tables(df, method_order: Sequence[str] = ()) -> tuple[list[Table], list[str]]:
    """The margins table of the store's finished cells, or none (and why) without Ours or another method."""
    import pandas as pd

    from weather_synth.settings import family_order

    ok = finished(df)
    ssim_protocol, lp = protocols(ok)
    ok, ceilings = ceiling.split(ok)
    ours_labels = ordered(ok.loc[ok["method"] == COMPARISON_OURS.method, "method_label"])
    if not ours_labels:
        return [], [f"margins (no {COMPARISON_OURS.method} cell to compare)"]
    ours = ours_labels[0]  # with several presets, the first (the others are compared as methods of their own)
    others = [m for m in ordered(ok["method_label"], method_order) if m != ours]
    means: dict[tuple[str, str, str], dict] = {}
    for weather, sub in ok.groupby("weather", sort=False):
        seeds = _seed_psnr(sub)
        for (m, s), (vals, _) in scene_means(sub, "method_label").items():
            means[(weather, m, s)] = dict(vals, seeds=seeds[(m, s)])
    weathers = ordered(ok["weather"], family_order())
    preset = ok.loc[ok["method_label"] == ours, "preset"].iloc[0]
    reference = ceilings[ceilings["preset"] == preset]
    if len(reference):
        clean = ceiling.label(reference["method_label"].iloc[0])
        seeds = _seed_psnr(reference)
        for (_, s), (vals, _) in ceiling.preset_means(reference).items():
            means.update({(w, clean, s): dict(vals, seeds=seeds[(reference["method_label"].iloc[0], s)])
                          for w in weathers})
        others.append(clean)
    if not others:
        return [], [f"margins (no method besides {ours} to compare with)"]

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
    spread = any(finite(r.values.get((o, SEED_SD.key))) for r in rows for o in others)
    columns = (*COLUMNS, SEED_SD) if spread else COLUMNS
    title = f"{COMPARISON_OURS.label} against each other method"
    notes = [f"Over the scenes both methods have (means over seeds): ΔPSNR and ΔSSIM = Ours minus the other, ΔLPIPS "
             f"= the other minus Ours, so positive is Ours better; won = scenes where Ours' PSNR is the higher. "
             f"{ALL} = every scene and setting. "
             + ("±seed = sample sd over the training seeds (both methods, every scene of the row) of the ΔPSNR "
                "computed seed by seed (a one-seed margin moves by about this much; the mean over n seeds by this / "
                "sqrt(n)). " if spread else "")
             + f"SSIM protocol: {ssim_protocol}; LPIPS: {lp}; {COMPARISON_OURS.note()}"]
    if len(reference):
        notes.append(f"{clean} = the clean ceiling: {CEILING_METHOD} trained on the scene's clean training views "
                     "(same views, split, preset and seeds); its group is Ours' gap to it, in the same signs (below "
                     "zero: what the weather costs Ours)")
    mixed = mixed_note(pd.concat([ok, reference]) if len(reference) else ok)
    if mixed:
        notes.append(mixed)
    return [Table("margins", "margins", title, columns=columns, groups=others, blocks=[Block(rows)],
                  lead=("Setting",), notes=notes, label="tab:nimbus-bench-margins", caption_lead="Margins: ",
                  wide=True, what=f"ours: {title}", csv=CSV,
                  fields={"ssim_protocol": ssim_protocol, "lpips_net": lp})], []


def _seed_psnr(frame) -> dict[tuple[str, str], dict[int, float]]:
    """(method, scene label) -> ``seed -> PSNR`` of the finished cells (records of one setting), grouped as
    :func:`~benchmark.tables.results.scene_means` groups them."""
    return {(m, s): {int(k): float(v) for k, v in zip(g["seed"], g["psnr"]) if finite(v)}
            for (m, s), g in frame.groupby(["method_label", "scene_label"], sort=False)}


def paper() -> dict[str, Table]:
    """None: the paper's numbers are other scenes (its per-weather tables are beside ours)."""
    return {}
