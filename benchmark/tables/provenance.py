"""Where and with what the figures were made: the counted cells by device, CPU ISA, torch and code (``provenance``).

A store can be filled over several sessions, machines or commits (a grid resumed elsewhere, a
GPU lease for some cells).  A figure can move with the CPU's vector ISA (AVX2 / AVX-512 round
reductions differently), the device (a CUDA cell rasterises with gsplat) and the code, so a
table whose cells mix them must say so.  Layout: one table, a row per combination of device,
CPU ISA, torch and code (the source commit, ``+modified`` for uncommitted code changes, or the
release where the record has no commit) among the cells the tables count (their latest ``ok``
records); columns: the number of cells, their settings, methods, the rasterizer backends that rendered them
(``gsplat``, ``cpp``, ``torch``; records older than the field: not recorded), and the days they finished.
Its notes also check that every method of a scene and setting trained on the same synthesised
input (one dataset manifest sha256): data made again on another machine may differ in its bytes.

:func:`mixed_note` is the sentence the per-weather tables add when their own cells mix these; where they mix
devices it names the cells that ran on the less common one.
There is no paper counterpart.
"""

from __future__ import annotations

from typing import Sequence

from benchmark.tables.model import Block, Column, LongFormat, Row, Table
from benchmark.tables.results import finished, ordered

KEY = "provenance"
TITLE = "Where the figures were made: cells by device, CPU ISA, torch and code"
COLUMNS = (
    Column("cells", "cells", "cells", 0),
    Column("settings", "settings", "settings", align="left"),
    Column("methods", "methods", "methods", align="left"),
    Column("rasterizer", "rasterizer", "rasterizer", align="left"),
    Column("finished", "finished (UTC)", "finished (UTC)", align="left"),
)
CSV = LongFormat("provenance.csv", "the counted cells by device, CPU ISA, torch and code",
                 ("table", "device", "cpu_isa", "torch", "code", "cells", "settings", "methods", "rasterizer",
                  "finished"),
                 group_field="group")
NOT_RECORDED = "not recorded"


def machine(record: dict) -> tuple[str, str, str, str]:
    """(device, CPU ISA, torch, code) of one store record; ``not recorded`` for what an old record lacks."""
    versions = record.get("versions")
    versions = versions if isinstance(versions, dict) else {}  # a hand-edited or foreign store: not recorded
    code = versions.get("nimbus_commit") or (f"release {versions['nimbus']}" if versions.get("nimbus") else None)
    return (str(record.get("device") or NOT_RECORDED), str(versions.get("cpu_isa") or NOT_RECORDED),
            str(versions.get("torch") or NOT_RECORDED), str(code or NOT_RECORDED))


def machine_label(key: tuple[str, str, str, str]) -> str:
    """``cpu (avx512), torch 2.13.0+cpu, code 8a4dbe657a05``."""
    device, isa, torch, code = key
    return f"{device} ({isa}), torch {torch}, code {code}"


def inputs(frame) -> dict[tuple[str, str], list[str]]:
    """(scene label, setting) -> the distinct dataset manifest sha256s its counted cells trained on."""
    out: dict[tuple[str, str], list[str]] = {}
    scene_column = "scene_label" if "scene_label" in frame else "scene"
    for (scene, weather), g in frame.groupby([scene_column, "weather"], sort=False):
        out[(scene, weather)] = sorted({str(h) for h in g["input_sha256"] if isinstance(h, str) and h})
    return out


def mixed_note(frame) -> str | None:
    """A sentence for a table whose cells (``frame``: finished records) come from several machines / codes or
    whose methods saw different inputs of one scene and setting; None when they do not."""
    parts = []
    keys = {machine(r) for r in frame["record"]}
    if len(keys) > 1:
        parts.append(f"its cells come from {len(keys)} device / CPU ISA / torch / code combinations, which can move "
                     "a figure by themselves")
    parts.extend(_other_devices(frame))
    split = [f"{scene} {weather}" for (scene, weather), hashes in inputs(frame).items() if len(hashes) > 1]
    if split:
        parts.append(f"the methods of {', '.join(split)} trained on different synthesised inputs")
    if not parts:
        return None
    return "Provenance: " + "; ".join(parts) + f" (see {KEY}.md)"


def _other_devices(frame) -> list[str]:
    """Where the cells ran on more than one device: which cells ran on each device but the most common one, as
    ``12 cells ran on cuda (the rest on cpu): nimbus-paper garden S, H+R; street H`` (the device moves a figure
    more than the code does, so a reader must find those cells without opening the provenance table)."""
    from weather_synth.settings import family_order

    scene_column = "scene_label" if "scene_label" in frame else "scene"
    device = frame["record"].map(lambda r: machine(r)[0])
    counts = device.value_counts(sort=False)
    if len(counts) < 2:
        return []
    common = max(counts.index, key=lambda d: (counts[d], d == "cpu"))  # a tie goes to the CPU
    scene_order = ordered(frame[scene_column])
    out = []
    for other in [d for d in counts.index if d != common]:
        sub = frame[device == other]
        methods = []
        for method, g in sub.groupby("method", sort=False):
            by_scene = dict(tuple(g.groupby(scene_column, sort=False)))
            scenes = [f"{s} {', '.join(ordered(by_scene[s]['weather'], family_order()))}"
                      for s in scene_order if s in by_scene]
            methods.append(f"{method} {'; '.join(scenes)}")
        n = len(sub)
        cells = f"{n} cell{'s' if n != 1 else ''}"
        where = f"{'has' if n == 1 else 'have'} no device recorded" if other == NOT_RECORDED else f"ran on {other}"
        out.append(f"{cells} {where} (the rest on {common}): {' | '.join(methods)}")
    return out


def _span(times) -> str:
    days = sorted({str(t)[:10] for t in times if isinstance(t, str) and t})
    return "–".join(dict.fromkeys([days[0], days[-1]])) if days else NOT_RECORDED


def _rasterizers(records) -> str:
    """The rasterizer backends the cells rendered with (records before the field existed: not recorded)."""
    return ", ".join(dict.fromkeys(str(r.get("rasterizer") or NOT_RECORDED) for r in records))


def tables(df, method_order: Sequence[str] = ()) -> tuple[list[Table], list[str]]:
    """The provenance table of the store's counted cells (never skipped: a store with a finished cell has one)."""
    from weather_synth.settings import family_order

    ok = finished(df)
    ok = ok.assign(_machine=[machine(r) for r in ok["record"]])
    rows = []
    for key, g in ok.groupby("_machine", sort=False):
        device, isa, torch, code = key
        settings = ", ".join(ordered(g["weather"], family_order()))
        methods = ", ".join(ordered(g["method"], method_order))
        rows.append(Row(machine_label(key),
                        {("", "cells"): str(len(g)), ("", "settings"): settings, ("", "methods"): methods,
                         ("", "rasterizer"): _rasterizers(g["record"]), ("", "finished"): _span(g["finished_at"])},
                        fields={"device": device, "cpu_isa": isa, "torch": torch, "code": code}))
    notes = [f"{len(ok)} counted cells (each cell's latest ok record); code = the source commit the cell ran at "
             "(+modified: with uncommitted code changes), or the release where the record names no commit"]
    if len(rows) > 1:
        notes.append("The cells come from several combinations: a figure can move with the CPU's vector ISA, the "
                     "device (CUDA cells rasterise with gsplat) and the code, so compare methods on cells of one "
                     "combination where a margin is small")
    found = inputs(ok)
    split = {k: v for k, v in found.items() if len(v) > 1}
    unknown = [k for k, v in found.items() if not v]
    if split:
        notes.append("Inputs DIFFER: " + "; ".join(
            f"{scene} {weather}: {len(h)} dataset manifests ({', '.join(x[:12] for x in h)})"
            for (scene, weather), h in split.items())
            + ": those methods did not train on the same synthesised bytes (data made again elsewhere); "
            "rerun them on one data folder to compare them exactly")
    else:
        notes.append(f"Inputs: the methods of each scene and setting trained on one synthesised input "
                     f"(one dataset manifest sha256; {len(found) - len(unknown)} scene-settings)")
    if unknown:
        notes.append(f"{len(unknown)} scene-settings have no input hash recorded")
    table = Table(KEY, KEY, TITLE, COLUMNS, groups=[""], blocks=[Block(rows)], lead=("Device (ISA), torch, code",),
                  group_heads=False, notes=notes, label="tab:nimbus-bench-provenance",
                  what="ours: the counted cells by device, CPU ISA, torch and code, and the input check",
                  csv=CSV, fields={"table": KEY})
    return [table], []


def paper() -> dict[str, Table]:
    """No paper counterpart."""
    return {}
