"""The plain-text summary ``nimbus-bench run`` prints at the end: one line per weather setting x method.

With clean-ceiling records (:mod:`benchmark.tables.ceiling`) the ceiling is the first line (setting
``clean``, method 3dgs) and a ``ΔPSNR`` column gives each line's gap to it.
"""

from __future__ import annotations

from typing import Sequence

from benchmark.cell import CEILING, CEILING_METHOD
from benchmark.tables import ceiling
from benchmark.tables.results import ordered, protocols
from nimbus.errors import NimbusError


def summary_table(df, method_order: Sequence[str] = ()) -> str:
    """Plain-text table: mean per weather setting x method over scenes and seeds, with train time.

    Error cells are counted, not averaged.  ``ΔPSNR`` (only with a finished ceiling cell) is the mean over
    the line's finished cells of the cell's PSNR minus its scene's ceiling (:func:`~.ceiling.cell_gaps`).
    """
    from weather_synth.settings import family_order

    if df is None or len(df) == 0:
        return "(no results)"
    ceilings = ceiling.split(df[df["status"] == "ok"])[1]
    gaps = len(ceilings) > 0
    # A setting of another protocol's family is named H+R+S@physical: the column widens to it.
    ww = max(7, *(len(str(w)) for w in df["weather"]))
    lines = [f"{'weather':<{ww}} {'method':<16} {'cells':>5} {'PSNR':>7} {'SSIM':>6} {'LPIPS':>6} {'train s':>8} "
             f"{'errors':>6}" + (f" {'ΔPSNR':>6}" if gaps else "")]
    for w in ordered(df["weather"], (CEILING, *family_order())):
        sub = df[df["weather"] == w]
        for m in ordered(sub["method"], method_order):
            g = sub[sub["method"] == m]
            ok = g[g["status"] == "ok"]

            def mean(col: str, spec: str) -> str:
                v = ok[col].astype(float)
                return "n/a" if len(v) == 0 or v.isna().any() else format(v.mean(), spec)

            line = (f"{w:<{ww}} {m:<16} {len(g):>5} {mean('psnr', '7.2f'):>7} {mean('ssim', '6.3f'):>6} "
                    f"{mean('lpips', '6.3f'):>6} {mean('train_time_s', '8.1f'):>8} {len(g) - len(ok):>6}")
            if gaps and w != CEILING:
                gap = ceiling.mean_gap(ok, ceilings)
                line += f" {'n/a' if gap is None else format(gap, '+6.2f'):>6}"
            lines.append(line)
    ok = df[df["status"] == "ok"]
    if len(ok):
        try:
            ssim_protocol, lp = protocols(ok.copy())
            lines.append(f"PSNR/SSIM/LPIPS against the clean test views; SSIM protocol: {ssim_protocol}; "
                         f"LPIPS: {lp}")
        except NimbusError as e:
            lines.append(f"note: {e}")
    if gaps:
        lines.append(f"{CEILING} = the clean ceiling ({CEILING_METHOD} trained on the clean views); ΔPSNR = PSNR "
                     "minus the ceiling's of the same scene and preset, dB (n/a: a scene without one)")
    return "\n".join(lines)
