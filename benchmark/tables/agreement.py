"""Do two results stores agree on the cells they share? (``nimbus-bench compare``)

The same cell (scene, size, setting, method, preset, seed) run on another device, CPU, torch or
code: does a figure move, and by how much, and does it change which method wins?  This answers
"can I trust my GPU's numbers beside my CPU's" and "did my change move the benchmark" without
subtracting by hand.

Layout: one table, a block per scene and setting (the cells both stores have), a row per method;
columns: PSNR in store A and in store B, then ``ΔPSNR``, ``ΔSSIM``, ``ΔLPIPS`` (B minus A, as
measured: positive ΔPSNR is B higher), ``time B/A`` (training seconds; devices run different
numbers of cells at once, so a throughput figure only where both ran alike) and ``input``:
``same`` when both trained on one synthesised input (one dataset manifest sha256), ``DIFFERS``
when the data was made again and came out other bytes (then a difference is not the device's
alone).  Its notes: what each store ran on (:func:`~benchmark.tables.provenance.machine_label`), the
mean and largest differences, the cells only one store has, and, per block, whether the methods'
order by PSNR is the same in both; a pair of methods that swaps places is named with its two
margins.  The stores must score alike (one SSIM protocol, one LPIPS network): otherwise SSIM and
LPIPS are not comparable, and the comparison is refused.
"""

from __future__ import annotations

from itertools import combinations
from typing import Sequence

from benchmark.tables.model import Block, Column, LongFormat, Row, Table, finite
from benchmark.tables.provenance import machine, machine_label
from benchmark.tables.results import finished, ordered, protocols
from nimbus.errors import NimbusError

KEY = "compare"
#: The columns after the two PSNRs, B minus A.
DELTAS = (("psnr", "d_psnr", "ΔPSNR", r"$\Delta$PSNR", 2), ("ssim", "d_ssim", "ΔSSIM", r"$\Delta$SSIM", 3),
          ("lpips", "d_lpips", "ΔLPIPS", r"$\Delta$LPIPS", 3))
CSV_COLUMNS = ("table", "scene", "weather", "method", "psnr_a", "psnr_b", "d_psnr", "d_ssim", "d_lpips",
               "time_ratio", "input")
#: Cells whose identity is the same in both stores: one ``cell_id`` (scene, size, setting, method, preset,
#: seed and any overrides' hash).
MATCH = "cell_id"


def _columns(names: tuple[str, str]) -> tuple[Column, ...]:
    a, b = names
    return (Column("psnr_a", f"PSNR {a}", f"PSNR {a}", 2), Column("psnr_b", f"PSNR {b}", f"PSNR {b}", 2),
            *(Column(key, text, latex, dec) for _, key, text, latex, dec in DELTAS),
            Column("time_ratio", f"time {b}/{a}", f"time {b}/{a}", 2),
            Column("input", "input", "input", align="center"))


def _value(row, key: str) -> float | None:
    v = row[key]
    v = None if v is None else float(v)
    return v if finite(v) else None


def _input(ha, hb) -> str:
    """``same`` / ``DIFFERS`` for two dataset manifest sha256s; ``not recorded`` where either record lacks one."""
    if not (isinstance(ha, str) and ha and isinstance(hb, str) and hb):
        return "not recorded"
    return "same" if ha == hb else "DIFFERS"


def _diff(a: float | None, b: float | None) -> float | None:
    return b - a if a is not None and b is not None else None


def _machines(ok) -> str:
    keys = list(dict.fromkeys(machine(r) for r in ok["record"]))
    return "; ".join(machine_label(k) for k in keys)


def _swaps(block: list[tuple[str, int, float | None, float | None]], a: str, b: str) -> list[str]:
    """The method pairs of one block (``(label, seed, PSNR in a, PSNR in b)`` rows) whose PSNR order differs
    between the stores; methods are compared seed by seed, and a tie at 0.01 dB is no order."""
    out = []
    for (m1, s1, a1, b1), (m2, s2, a2, b2) in combinations(block, 2):
        if s1 != s2 or None in (a1, b1, a2, b2):
            continue
        da, db = round(a1 - a2, 2), round(b1 - b2, 2)
        if da * db < 0:
            out.append(f"{m1} vs {m2} ({a}: {da:+.2f} dB, {b}: {db:+.2f} dB)")
    return out


def compare(df_a, df_b, names: tuple[str, str] = ("A", "B"),
            method_order: Sequence[str] = ()) -> tuple[Table, list[str]]:
    """The comparison table of two stores (:func:`benchmark.store.load_results` frames) and its summary lines.

    Raises NimbusError when either store has no finished cell, the two share none, or they score
    with different SSIM protocols or LPIPS networks.
    """
    from weather_synth.settings import family_order

    a, b = names
    ok_a, ok_b = finished(df_a), finished(df_b)
    (ssim_a, lp_a), (ssim_b, lp_b) = protocols(ok_a), protocols(ok_b)
    if ssim_a != ssim_b:
        raise NimbusError(f"the stores score SSIM differently ({a}: {ssim_a}, {b}: {ssim_b}); compare stores of one "
                          "--ssim protocol")
    net_a, net_b = (sorted(set(o["lpips_net"].dropna())) for o in (ok_a, ok_b))
    if net_a and net_b and net_a != net_b:
        raise NimbusError(f"the stores score LPIPS with different networks ({a}: {net_a[0]}, {b}: {net_b[0]}); "
                          "compare stores of one --lpips")
    by_b = {r[MATCH]: r for _, r in ok_b.iterrows()}
    shared = ok_a[ok_a[MATCH].isin(by_b)]
    if len(shared) == 0:
        raise NimbusError(f"the stores share no finished cell ({a}: {len(ok_a)} cells, {b}: {len(ok_b)}); a cell "
                          "matches on scene, size, setting, method, preset and seed: run the same grid in both")
    settings = ordered(shared["weather"], family_order())
    methods = ordered(shared["method"], method_order)
    blocks, per_block, rows_all = [], {}, []
    for scene in ordered(shared["scene_label"]):
        for weather in settings:
            g = shared[(shared["scene_label"] == scene) & (shared["weather"] == weather)]
            if len(g) == 0:
                continue
            rows, psnrs = [], []
            for method in methods:
                hit = g[g["method"] == method]
                if len(hit) == 0:
                    continue
                for _, ra in hit.iterrows():
                    rb = by_b[ra[MATCH]]
                    values = {("", "psnr_a"): _value(ra, "psnr"), ("", "psnr_b"): _value(rb, "psnr")}
                    for metric, key, *_ in DELTAS:
                        values[("", key)] = _diff(_value(ra, metric), _value(rb, metric))
                    ta, tb = _value(ra, "train_time_s"), _value(rb, "train_time_s")
                    values[("", "time_ratio")] = tb / ta if ta and tb is not None else None
                    values[("", "input")] = _input(ra["input_sha256"], rb["input_sha256"])
                    label = method if ra["seed"] == 0 else f"{method} (seed {ra['seed']})"
                    rows.append(Row(label, values, fields={"method": method, "scene": scene, "weather": weather}))
                    psnrs.append((label, ra["seed"], values[("", "psnr_a")], values[("", "psnr_b")]))
                    rows_all.append((f"{scene} {weather} {label}", values))
            blocks.append(Block(rows, name=f"{scene} {weather}"))
            per_block[f"{scene} {weather}"] = psnrs
    matched_b = ok_b[ok_b[MATCH].isin(set(shared[MATCH]))]
    lines = [f"{a}: {_machines(shared)}", f"{b}: {_machines(matched_b)}"]
    only_a, only_b = len(ok_a) - len(shared), len(ok_b) - len(shared)
    lines.append(f"{len(shared)} cells in both stores; only in {a}: {only_a}, only in {b}: {only_b}")
    for metric, key, text, _, dec in DELTAS:
        ds = [(abs(v[("", key)]), v[("", key)], where) for where, v in rows_all if v[("", key)] is not None]
        if ds and not any(x for x, _, _ in ds):
            lines.append(f"{text} ({b} - {a}): exactly 0 in all {len(ds)} cells")
        elif ds:
            mean = sum(d for _, d, _ in ds) / len(ds)
            mean_abs = sum(x for x, _, _ in ds) / len(ds)
            _, worst, where = max(ds)
            lines.append(f"{text} ({b} - {a}): mean {mean:+.{dec}f}, mean |{text}| {mean_abs:.{dec}f}, largest "
                         f"{worst:+.{dec}f} ({where})")
    swapped = {k: _swaps(v, a, b) for k, v in per_block.items()}
    ranked = [k for k, v in per_block.items() if len(v) > 1]
    if ranked:
        same = [k for k in ranked if not swapped[k]]
        lines.append(f"Method order by PSNR: the same in {len(same)} of {len(ranked)} scene-settings"
                     + "".join(f"; {k}: {', '.join(swapped[k])}" for k in ranked if swapped[k]))
    differ = [where for where, v in rows_all if v[("", "input")] == "DIFFERS"]
    if differ:
        named = ", ".join(differ[:4]) + (", ..." if len(differ) > 4 else "")
        lines.append(f"Inputs DIFFER for {len(differ)} cells ({named}): the data was synthesised again and came out "
                     "other bytes, so their differences are not the device's or code's alone")
    elif all(v[("", "input")] == "same" for _, v in rows_all):
        lines.append("Inputs: every shared cell trained on the same synthesised bytes in both stores")
    notes = [*lines, f"Δ = {b} minus {a} as measured (positive ΔPSNR / ΔSSIM: {b} higher; positive ΔLPIPS: {b} "
             f"worse); time {b}/{a}: training seconds, which depend on how many cells each machine ran at once",
             f"Protocol: SSIM {ssim_a}, LPIPS {lp_a if lp_a == lp_b else f'{a}: {lp_a}; {b}: {lp_b}'}"]
    csv = LongFormat("compare.csv", f"the shared cells of stores {a} and {b}, figure by figure", CSV_COLUMNS,
                     group_field="group")
    table = Table(KEY, KEY, f"Store {b} against store {a}: the cells both ran", _columns(names), groups=[""],
                  blocks=blocks, lead=("Method", "Scene, setting"), group_heads=False, notes=notes,
                  label="tab:nimbus-bench-compare", what=f"the shared cells of {a} and {b}, and their differences",
                  csv=csv, fields={"table": KEY})
    return table, lines
