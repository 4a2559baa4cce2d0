"""The decomposition table (``nimbus-bench decompose``): one run's learned layers against the ground truth, per band.

Built from the record :func:`benchmark.decompose.decompose_run` makes (``decompose.json``), so the table is
regenerated from its record and never from the model; rendered by the one writer
(:mod:`benchmark.tables.writer`).  One row per depth band (near, middle, far, sky, then all pixels); nothing
is ranked (the rows are parts of one run, not rivals).
"""

from __future__ import annotations

from benchmark.tables.model import Block, Column, Row, Table

#: Rows in order (the record's band names).
ROWS = ("near", "middle", "far", "sky", "all")
COLUMNS = (
    Column("pixels_pct", "Pixels %", r"Pixels \%", 1),
    Column("t_true", "t true", "$t$", 3),
    Column("t_bias", "T bias", "$T$ bias", 3),
    Column("t_mae", "T MAE", "$T$ MAE", 3),
    Column("airlight_error_r", "A err R", "$A$ err R", 3),
    Column("airlight_error_g", "A err G", "$A$ err G", 3),
    Column("airlight_error_b", "A err B", "$A$ err B", 3),
    Column("airlight_bias", "A bias", "$A$ bias", 3),
    Column("clean_bias_r", "I bias R", r"$\hat I$ bias R", 3),
    Column("clean_bias_g", "I bias G", r"$\hat I$ bias G", 3),
    Column("clean_bias_b", "I bias B", r"$\hat I$ bias B", 3),
    Column("mse_share_pct", "MSE %", r"MSE \%", 1),
    Column("psnr", "PSNR", "PSNR", 2),
    Column("veil_gain_db", "Veil +dB", "Veil +dB", 2),
)
NOTES = [
    "Training views re-rendered by the run's model against the synthesiser's layers; errors are learned minus true",
    "Bands: near / middle / far are equal thirds of the surface pixels' ray-distance range (printed in the row), "
    "sky is the sky mask",
    "T bias, T MAE: mean of T - t and of its absolute value; A err: the effective airlight sum P / sum (1 - T) "
    "minus the true airlight weighted alike, per channel, A bias its mean over the channels (– where the learned "
    "medium veils nothing)",
    "I bias: mean of the clean render minus the clean view per channel; MSE %: the band's share of the summed "
    "squared error; Veil +dB: PSNR gained by removing the band's per-channel mean error (PSNR is before)",
]


def _row_values(band: dict) -> dict[str, float | None]:
    def pct(v):
        return None if v is None else 100.0 * v

    def channel(key: str, i: int):
        v = band.get(key)
        return None if v is None else v[i]

    values = {"pixels_pct": pct(band.get("pixel_share")), "mse_share_pct": pct(band.get("mse_share"))}
    for key in ("t_true", "t_bias", "t_mae", "airlight_bias", "psnr", "veil_gain_db"):
        values[key] = band.get(key)
    for i, c in enumerate("rgb"):
        values[f"airlight_error_{c}"] = channel("airlight_error", i)
        values[f"clean_bias_{c}"] = channel("clean_bias", i)
    return values


def row_label(name: str, edges: list[float]) -> str:
    """A band's label with its ray-distance range (sky and all have none)."""
    spans = {"near": (0, 1), "middle": (1, 2), "far": (2, 3)}
    if name not in spans or len(edges) != 4:
        return name
    lo, hi = (edges[i] for i in spans[name])
    return f"{name} ({lo:.3g}-{hi:.3g})"


def decompose_table(record: dict) -> Table:
    """The table of one ``decompose.json`` record."""
    edges = record.get("depth", {}).get("edges") or []
    rows = []
    for name in ROWS:
        band = record["bands"].get(name)
        if band is None:
            continue
        rows.append(Row(row_label(name, edges), {("", k): v for k, v in _row_values(band).items()},
                        rule_before=name == "all", fields={"band": name}))
    title = (f"Decomposition of {record.get('method', '?')} on {record.get('setting', '?')}: "
             f"{record.get('views', '?')} training views at iteration {record.get('iteration', '?')}")
    return Table("decompose", "decompose", title, COLUMNS, [""], [Block(rows, name=str(record.get("setting", "")))],
                 lead=("Band", "Setting"), notes=list(NOTES), group_heads=False, wide=True,
                 fields={"run": record.get("run"), "method": record.get("method")})
