"""The paper's per-weather comparison tables, ours from the results store and the paper's own numbers.

Layout (``nimbusgs.tex``, tables ``tab:dehaze`` / ``tab:derain`` / ``tab:desnow`` / ``tab:mix`` and the
supplementary ``tab:h+r`` / ``tab:h+s`` / ``tab:r+s``): one table per weather setting, methods as
rows, scenes as column groups plus an ``Average`` group, each group PSNR↑ / SSIM↑ / LPIPS↓.
Values are means over the seeds of a cell; ``Average`` is the mean over scenes and is left
empty for a method missing a scene.  Best and second best are marked per column
(:func:`benchmark.tables.model.rank_marks`).  Every table states its SSIM protocol and LPIPS network.

The "Ours" row is :data:`~benchmark.tables.results.COMPARISON_OURS` (``nimbus``, components chosen
by ``auto``), labelled with its configuration; the ablation tables' "Ours" is ``nimbus-full``, and
each table's note says both.

When its records carry the degraded input's own score (:mod:`benchmark.tables.inputs`), a table has one
more block under its methods: the degraded test views themselves, scored alike (``degraded input (test
views)``).  When the store has clean-ceiling records (:mod:`benchmark.tables.ceiling`), each table has two
more blocks after that: the ceiling (3DGS trained on the clean views) and each method's gap to it.  The
long-format CSV has the input's and the ceiling's lines (method ``degraded input (test views)``, ``3DGS
(clean views)``), not the gaps.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

from benchmark.data import PAPER_DIR, read_csv
from benchmark.tables import ceiling, inputs
from benchmark.tables.model import AVERAGE, Block, LongFormat, Row, Table
from benchmark.tables.provenance import mixed_note
from benchmark.tables.results import (COMPARISON_OURS, METRIC_COLUMNS, METRICS, average, finished, ordered, protocols,
                                      scene_means)

if TYPE_CHECKING:  # importlib.resources.abc is Python 3.11+
    from importlib.resources.abc import Traversable

CSV = LongFormat("comparisons.csv", "all method comparisons, long format",
                 ("weather", "protocol", "method", "scene", *METRICS, *(f"{k}_mark" for k in METRICS), "seeds",
                  "ssim_protocol", "lpips_net"))
CAPTION_LEAD = "Quantitative comparison: "


def weather_caption(weather: str) -> str:
    """``haze (H)``: a weather setting's description and name; ``haze (H), physical protocol: one medium per
    scene (...)`` for a setting of another protocol's family (``H@physical``)."""
    from weather_synth.config import PROTOCOL_SUMMARIES
    from weather_synth.settings import DEFAULT_PROTOCOL, parse_family_setting

    family = parse_family_setting(weather)
    caption = f"{family.setting.description} ({family.setting.name})"
    if family.protocol != DEFAULT_PROTOCOL:
        caption += f", {family.protocol} protocol: {PROTOCOL_SUMMARIES[family.protocol]}"
    return caption


def table_key(weather: str) -> str:
    """File stem of a setting's table: ``weather_H+R``, ``weather_H+R_physical`` in the physical family."""
    from weather_synth.settings import FAMILY_SEPARATOR

    return "weather_" + weather.replace(FAMILY_SEPARATOR, "_")


def _table(weather: str, key: str, label: str, scenes: list[str], rows: list[Row], extra: Sequence[Block] = (),
           **kw) -> Table:
    """The table of one setting: the method rows, then the ``extra`` blocks (the input's, the clean ceiling's)."""
    tag = table_key(weather)[len("weather_"):].replace("+", "-").replace("_", "-")
    blocks = [Block(rows, f"trained on {weather}" if extra else ""), *extra]
    return Table(key, weather, columns=METRIC_COLUMNS, groups=[*scenes, AVERAGE], blocks=blocks,
                 lead=("Method", "Rows") if extra else ("Method",), label=f"tab:nimbus-bench-{label}{tag}",
                 caption_lead=CAPTION_LEAD, wide=True, **kw)


def synthesis_note(frame, protocol: str, summary: str) -> str:
    """Who degraded a setting's images: the synthesiser (its protocol), or the dataset trees given to ``--scenes``
    (their own images: no protocol of ours), or both, naming the trees' scenes."""
    kinds = frame["scene_kind"] if "scene_kind" in frame else None
    trees = [] if kinds is None else ordered(frame.loc[kinds == "tree", "scene_label"])
    ours = f"Synthesis protocol: {protocol} ({summary})"
    if not trees:
        return ours
    theirs = "degraded images of the dataset tree(s) given to --scenes, not made by nimbus-synth"
    if len(trees) == frame["scene_label"].nunique():
        return f"Weather: the {theirs}"
    return f"{ours}; {', '.join(trees)}: the {theirs}"


def tables(df, method_order: Sequence[str] = ()) -> tuple[list[Table], list[str]]:
    """One table per weather setting of the store's finished cells (no layout is ever skipped).

    A setting of another synthesis protocol's family (``H@physical``) is a setting of its own:
    its table follows the default family's seven.  Methods in ``method_order`` are listed
    first, in that order; the others follow in store order.
    """
    import pandas as pd

    from weather_synth.config import PROTOCOL_SUMMARIES
    from weather_synth.settings import family_order, parse_family_setting

    ok = finished(df)
    ssim_protocol, lp = protocols(ok)  # the ceiling's records too: its row is printed beside the others
    ok, ceilings = ceiling.split(ok)
    out = []
    for weather in ordered(ok["weather"], family_order()):
        sub = ok[ok["weather"] == weather]
        scenes = ordered(sub["scene_label"])
        cells = scene_means(sub, "method_label")
        rows = []
        for m in ordered(sub["method_label"], method_order):
            ours = sub.loc[sub["method_label"] == m, "method"].iloc[0] == COMPARISON_OURS.method
            row = Row(COMPARISON_OURS.row_label(m) if ours else m, fields={"method": m})
            for s in scenes:
                if (m, s) in cells:
                    means, n = cells[(m, s)]
                    row.values.update({(s, k): means[k] for k in METRICS})
                    row.group_fields[s] = {"seeds": n}
            for k in METRICS:
                row.values[(AVERAGE, k)] = average([row.values.get((s, k)) for s in scenes])
            rows.append(row)
        presets = dict(zip(sub["method_label"], sub["preset"]))
        shown = ceilings[ceilings["scene_label"].isin(scenes) & ceilings["preset"].isin(set(presets.values()))]
        given = inputs.blocks(sub, scenes)
        ceilings_shown = ceiling.blocks(rows, presets, shown, scenes)
        extra = [*given, *ceilings_shown]
        caption = weather_caption(weather)
        protocol = parse_family_setting(weather).protocol
        notes = [f"{synthesis_note(sub, protocol, PROTOCOL_SUMMARIES[protocol])}; SSIM protocol: "
                 f"{ssim_protocol}; LPIPS: {lp}; mean over seeds, Average = mean over scenes; {COMPARISON_OURS.note()}"]
        if given:
            notes.append(inputs.note())
        if ceilings_shown:
            notes.append(ceiling.note())
        mixed = mixed_note(pd.concat([sub, shown]) if ceilings_shown else sub)
        if mixed:
            notes.append(mixed)
        out.append(_table(weather, table_key(weather), "", scenes, rows, extra, title=caption, notes=notes,
                          what=f"ours: method comparison, {caption}", csv=CSV,
                          fields={"weather": weather, "protocol": protocol, "ssim_protocol": ssim_protocol,
                                  "lpips_net": lp}))
    return out, []


def paper(folder: Traversable = PAPER_DIR) -> dict[str, Table]:
    """The paper's per-weather tables by weather setting (package data; empty when ``folder`` is absent).

    These are the paper's numbers on the paper's (real) scenes, labelled as such; they
    share the layout of ours, not the data.
    """
    out: dict[str, Table] = {}
    if not folder.is_dir():
        return out
    for f in sorted((f for f in folder.iterdir() if f.name.endswith(".csv")), key=lambda f: f.name):
        records = read_csv(f)
        if not records:
            continue
        label, weather = records[0]["table_label"], records[0]["weather"]
        rows = {m: Row(m) for m in dict.fromkeys(r["method"] for r in records)}
        for r in records:
            rows[r["method"]].values.update({(r["scene"], k): float(r[k]) for k in METRICS})
        scenes = [s for s in dict.fromkeys(r["scene"] for r in records) if s != AVERAGE]
        out[weather] = _table(
            weather, f"paper_{weather}", "paper-", scenes, list(rows.values()),
            title=f"the paper's reported numbers on the paper's data ({label}, {weather_caption(weather)})",
            notes=[f"Transcribed from nimbusgs.tex {label}; NOT results of this benchmark (other scenes); "
                   "SSIM as 3DGS evaluates it, LPIPS VGG"])
    return out
