"""What the tables read from the results store: finished cells, labels, protocols, means.

The quality columns (PSNR, SSIM, LPIPS) are defined here once for every layout that shows them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

from benchmark.tables.model import Column, finite
from nimbus.errors import NimbusError

#: PSNR / SSIM / LPIPS as the paper prints them (its decimals; values are ranked as printed).
METRIC_COLUMNS = (
    Column("psnr", "PSNR↑", r"PSNR$\uparrow$", 2, higher_is_better=True),
    Column("ssim", "SSIM↑", r"SSIM$\uparrow$", 3, higher_is_better=True),
    Column("lpips", "LPIPS↓", r"LPIPS$\downarrow$", 3, higher_is_better=False),
)
METRICS = tuple(c.key for c in METRIC_COLUMNS)


@dataclass(frozen=True)
class Ours:
    """The method a table's "Ours" row shows, named with its configuration in the row label.

    The per-weather tables compare the method a user runs (``nimbus``, components chosen by
    ``auto``); the ablations change one thing of every component forced on (``nimbus-full``).
    Each table's label says which, so the two are never read as one configuration.

    Attributes
    ----------
    method : str
        Registered method (:mod:`nimbus.methods.registry`) whose results fill the row.
    configuration : str
        Its configuration in a few words (``components by auto``, ``csm+plm+ggs``).
    """

    method: str
    configuration: str

    @property
    def label(self) -> str:
        """``Ours (nimbus: components by auto)``."""
        return f"Ours ({self.method}: {self.configuration})"

    def row_label(self, method_label: str) -> str:
        """The label of the row whose store label is ``method_label`` (:func:`labelled`: maybe `` (preset)``)."""
        return self.label + method_label[len(self.method):]

    def note(self) -> str:
        """What a table says under it about its "Ours" row, and the other layout's."""
        other, where = ((ABLATION_OURS, "ablation") if self == COMPARISON_OURS else
                        (COMPARISON_OURS, "per-weather comparison"))
        return (f"Ours = {self.method} ({self.configuration}); the {where} tables' Ours is {other.method} "
                f"({other.configuration})")


#: The per-weather comparisons' "Ours": NimbusGS as a user runs it.
COMPARISON_OURS = Ours("nimbus", "components by auto")
#: The ablations' "Ours": every component forced on, the base each ablation variant changes one thing of.
ABLATION_OURS = Ours("nimbus-full", "csm+plm+ggs")


def finished(df):
    """The store's ``ok`` records, with ``scene_label`` and ``method_label`` (NimbusError when there are none).

    Labels name the size / preset only when the store mixes several.
    """
    if df is None or len(df) == 0:
        raise NimbusError("the results store is empty; run `nimbus-bench run` first")
    ok = df[df["status"] == "ok"].copy()
    if len(ok) == 0:
        raise NimbusError("the results store has no finished cell (every record is an error); see `error` in "
                          "results.jsonl and rerun `nimbus-bench run`")
    return labelled(ok)


def labelled(ok):
    """``ok`` with ``scene_label`` and ``method_label`` columns (size / preset named only when mixed)."""
    multi_size = ok["size"].nunique() > 1
    multi_preset = ok["preset"].nunique() > 1
    ok["scene_label"] = ok["scene"] + (("-" + ok["size"]) if multi_size else "")
    ok["method_label"] = ok["method"] + ((" (" + ok["preset"] + ")") if multi_preset else "")
    return ok


def protocols(ok) -> tuple[str, str]:
    """(SSIM protocol, LPIPS description) of the finished records; NimbusError when they mix protocols."""
    ssim = sorted(set(ok["ssim_protocol"].dropna()))
    if len(ssim) > 1:
        raise NimbusError(f"the store mixes SSIM protocols ({', '.join(ssim)}); one table needs one protocol: "
                          "rerun the cells with one --ssim (or use a separate --root)")
    nets = sorted(set(ok["lpips_net"].dropna()))
    if len(nets) > 1:
        raise NimbusError(f"the store mixes LPIPS networks ({', '.join(nets)}); rerun with one --lpips")
    if not nets:
        lp = "not computed"
    elif ok["lpips"].isna().any():
        lp = (f"lpips-{nets[0]}-v0.1, missing for some cells (weights not set up: run "
              "`nimbus-bench setup-weights`, then rerun those cells with --rerun)")
    else:
        lp = f"lpips-{nets[0]}-v0.1"
    return (ssim[0] if ssim else "3dgs"), lp


def ordered(values: Iterable, preferred: Sequence[str] = ()) -> list[str]:
    """Distinct ``values`` in first-seen order, the ``preferred`` ones first (in their order)."""
    seen = list(dict.fromkeys(values))
    return [p for p in preferred if p in seen] + [v for v in seen if v not in preferred]


def scene_means(frame, method_column: str) -> dict[tuple[str, str], tuple[dict[str, float | None], int]]:
    """(method, scene label) -> (metric -> mean over seeds, or None where a seed lacks it; number of records)."""
    out = {}
    for (m, s), g in frame.groupby([method_column, "scene_label"], sort=False):
        means = {k: float(g[k].astype(float).mean()) if g[k].notna().all() else None for k in METRICS}
        out[(m, s)] = (means, len(g))
    return out


def average(values: Sequence[float | None]) -> float | None:
    """Mean of ``values``; None when there are none or one is missing (an average is never partial)."""
    return float(np.mean(values)) if values and all(finite(v) for v in values) else None
