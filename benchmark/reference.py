"""CI regression check: compare a tiny benchmark's figures with committed reference figures.

``nimbus-bench reference check --root ROOT --reference FILE`` fails (exit 1) when a cell's
quality dropped by more than the tolerance (PSNR, SSIM lower; LPIPS higher), when its
synthesised input changed by more than its tolerance (compared by content, see below), or
when a reference cell is missing or failed.  ``nimbus-bench reference update`` rewrites
FILE from the store, so a deliberate change shows as a diff of the reference file in review.

Synthesised input
    Each cell's degraded dataset is recorded by content: every degraded and clean image is
    summarised by its per-channel means over a :data:`CONTENT_GRID` of blocks, in 8-bit
    levels (:func:`image_fingerprint`), and the check allows :attr:`Tolerance.input_levels`
    (one level: synthesis promises the same pixels within 1/255 on any x86-64 CPU).  The
    manifest's sha256 is kept as information: its bytes may differ between CPUs or
    library builds without the pixels changing, so it never fails the check.

The regression grid
    :data:`REGRESSION_GRID` is the tiny benchmark CI runs (``tests/test_regression.py``,
    inside the README's ``python -m pytest``) against :data:`REGRESSION_REFERENCE`
    (``benchmark/data/regression_tiny.json``, package data).  ``nimbus-bench reference update
    --regression`` runs exactly that grid in a temporary folder and rewrites the file;
    ``check --regression`` runs it and checks, as the test does.

Determinism
    Scenes, synthesis and training seeds are fixed and the grid runs on the CPU with a
    fixed number of torch threads, so two runs on one machine give the same figures bit
    for bit.  The thread count is pinned because it matters: 1 instead of 2 threads
    changes the last bits of some kernels, which training amplifies (measured: up to
    0.17 dB PSNR / 0.004 LPIPS on one NimbusGS cell, < 4e-4 on the others).  Another
    CPU does the same: numpy, OpenBLAS and torch's MKL pick AVX-512, AVX2 or SSE kernels
    by CPU, whose rounding differs.  The tolerance (:class:`Tolerance`) is set from that
    spread, measured on one machine by emulating the other CPUs with the libraries'
    own dispatch switches (:data:`EMULATED_CPUS`); a deliberate change to training or
    synthesis is expected to move the figures by more and is recorded with ``update``.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from benchmark.data import REGRESSION_REFERENCE  # the committed figures of REGRESSION_GRID (package data)
from nimbus.errors import NimbusError

REFERENCE_FORMAT = "nimbus-bench-reference/1"
#: Metric key, :class:`Tolerance` field, +1 when higher is better (-1: lower is better).
METRICS = (("psnr", "psnr_db", 1), ("ssim", "ssim", 1), ("lpips", "lpips", -1))
#: Blocks (rows, columns) over which each input image's channel means are recorded.
CONTENT_GRID = (4, 4)
#: Recorded block means are in 1/CONTENT_SCALE of an 8-bit level (stored as 4 hex digits each).
CONTENT_SCALE = 100
#: Environment of each emulated CPU: the dispatch switches of numpy, OpenCV, torch (ATen, oneDNN),
#: OpenBLAS, glibc's maths and the compositing kernel.  Set before the libraries load (a fresh
#: process), they make an AVX-512 machine take the code paths of an AVX2-only or a pre-AVX CPU;
#: the tolerances below were measured this way (README, "Regression references").
EMULATED_CPUS = {
    "avx2": {
        "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR",
        "OPENCV_CPU_DISABLE": "AVX512-SKX,AVX512-COMMON,AVX512-ICL,AVX512-CLX,AVX512-CNL",
        "ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_ENABLE_INSTRUCTIONS": "AVX2",
        "OPENBLAS_CORETYPE": "Haswell", "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX512F,-AVX512DQ,-AVX512BW,-AVX512VL",
        "NIMBUS_CPU_ISA": "avx2",
    },
    "generic": {
        "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",
        "OPENCV_CPU_DISABLE": "SSE4.1,SSE4.2,POPCNT,AVX,FP16,AVX2,FMA3,AVX512-SKX,AVX512-COMMON,AVX512-ICL,"
                              "AVX512-CLX,AVX512-CNL",
        "ATEN_CPU_CAPABILITY": "default", "ONEDNN_MAX_CPU_ISA": "SSE41", "MKL_ENABLE_INSTRUCTIONS": "SSE4_2",
        "OPENBLAS_CORETYPE": "Nehalem",
        "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX512F,-AVX512DQ,-AVX512BW,-AVX512VL,-AVX2,-FMA,-AVX,-F16C",
        "NIMBUS_CPU_ISA": "generic",
    },
}


@dataclass(frozen=True)
class Tolerance:
    """How much worse a figure may get before the check fails.

    Stored in the reference file (these defaults apply when a new file is written for a store
    checked on the machine that made it; the regression grid's file uses
    :data:`CROSS_CPU_TOLERANCE`).  On the tiny regression grid, runs on one machine repeat bit
    for bit, 1 vs 2 threads moved PSNR by up to 0.17 dB and LPIPS by 0.004, and a different
    training seed moves PSNR by 0.02-1 dB.

    Attributes
    ----------
    psnr_db : float
        Allowed PSNR drop, dB.
    ssim : float
        Allowed SSIM drop.
    lpips : float
        Allowed LPIPS rise.
    input_levels : float
        Allowed change of any recorded block mean of the synthesised input, 8-bit levels.
    """

    psnr_db: float = 0.3
    ssim: float = 0.01
    lpips: float = 0.01
    input_levels: float = 1.0


@dataclass(frozen=True)
class RegressionGrid:
    """The tiny benchmark CI checks against :data:`REGRESSION_REFERENCE` (defined once, here).

    Attributes
    ----------
    scenes, weathers, methods : tuple of str
        Built-in scenes, weather settings and methods (every combination is a cell).
    preset, size : str
        Trainer preset and built-in scene size.
    seeds : tuple of int
        Training seeds.
    ssim_protocol, lpips_net : str
        Scoring protocols (the paper's).
    threads : int
        torch threads of the worker: fixed, so the figures do not depend on the core count.
    device : str
        Training device: the CPU, as in CI, whatever the developer's machine has.
    """

    scenes: tuple[str, ...] = ("garden", "street")
    weathers: tuple[str, ...] = ("H", "R+S")
    methods: tuple[str, ...] = ("nimbus", "3dgs")
    preset: str = "tiny"
    size: str = "tiny"
    seeds: tuple[int, ...] = (0,)
    ssim_protocol: str = "3dgs"
    lpips_net: str = "vgg"
    threads: int = 2
    device: str = "cpu"

    def cells(self) -> list:
        """The grid's :class:`benchmark.cell.Cell` list, in table order."""
        from benchmark.grid import build_cells

        return build_cells(self.scenes, self.weathers, self.methods, [self.preset], self.seeds, self.size)

    def options(self):
        """The :class:`benchmark.cell.CellOptions` its cells run with."""
        from benchmark.cell import CellOptions

        return CellOptions(self.ssim_protocol, self.lpips_net, self.threads, self.device)


REGRESSION_GRID = RegressionGrid()

#: The regression grid's tolerance: about twice the largest change measured between CPUs.  On one
#: AVX-512 machine, emulating an AVX2-only and a pre-AVX CPU (:data:`EMULATED_CPUS`) moved the grid's
#: figures by up to 0.50 dB PSNR, 0.017 SSIM and 0.030 LPIPS between any two of the three (per cell:
#: benchmark/data/README.md), and a real AVX2 machine moved one SSIM by 0.020 (issue 14); the
#: compositing kernel's clones moved nothing.
CROSS_CPU_TOLERANCE = Tolerance(psnr_db=1.0, ssim=0.04, lpips=0.06)


def run_regression(root: str | Path, grid: RegressionGrid = REGRESSION_GRID,
                   log: Callable[[str], None] | None = None):
    """Run every cell of ``grid`` afresh into ``root`` and return their records (:func:`load_results` rows).

    The cells run one after the other in one worker process (its own torch threads and
    state, whatever the caller's), always anew: a stale record in ``root`` is never reused.
    """
    from benchmark.grid import LocalExecutor, run_grid
    from benchmark.store import load_results

    cells = grid.cells()
    run_grid(cells, root, LocalExecutor(1), grid.options(), rerun=True, progress=False,
             log=log or (lambda s: None))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        df = load_results(root, latest=False)  # this run's record, even an error: not an older ok one
    df = df[df["cell_id"].isin({c.cell_id for c in cells})].drop_duplicates("cell_id", keep="last")
    return attach_input_content(df, root)


# --- the synthesised input, by content ----------------------------------------------------------
def image_fingerprint(path: str | Path) -> str:
    """An image's per-channel means over :data:`CONTENT_GRID` blocks, in 1/:data:`CONTENT_SCALE` of an
    8-bit level, as hex (4 digits per mean; rows, then columns, then R, G, B).

    Computed from the 8-bit values with exact integer sums, so it is the same on every machine;
    two images whose pixels differ by at most one level have block means within one level.
    """
    from nimbus.data.images import read_image

    levels = np.rint(read_image(path).astype(np.float64) * 255.0)
    h, w = levels.shape[:2]
    rows, cols = CONTENT_GRID
    means = []
    for i in range(rows):
        for j in range(cols):
            block = levels[i * h // rows:max((i + 1) * h // rows, i * h // rows + 1),
                           j * w // cols:max((j + 1) * w // cols, j * w // cols + 1)]
            means.extend(block.reshape(-1, 3).mean(axis=0))
    return "".join(f"{int(round(m * CONTENT_SCALE)):04x}" for m in means)


def decode_fingerprint(text: str) -> np.ndarray:
    """The block means (8-bit levels, float64) of an :func:`image_fingerprint` string."""
    return np.array([int(text[k:k + 4], 16) for k in range(0, len(text), 4)], np.float64) / CONTENT_SCALE


def input_fingerprint(data: str | Path) -> dict | None:
    """``{view name: {"image": fingerprint, "clean": fingerprint}}`` of a degraded setting folder (every view
    its manifest lists: the degraded image training reads and the clean image it is scored against), or
    None when the folder has no manifest or is no degraded setting (a clean-ceiling cell's clean scene, whose
    manifest lists no views)."""
    from nimbus.schemas import Schema, read_json_file
    from weather_synth.dataset import MANIFEST, read_setting_manifest

    data = Path(data)
    if not (data / MANIFEST).is_file():
        return None
    if "views" not in read_json_file(data / MANIFEST, Schema, "restore or regenerate the folder"):
        return None
    views = read_setting_manifest(data)["views"]
    return {v["name"]: {"image": image_fingerprint(data / v["image"]), "clean": image_fingerprint(data / v["clean"])}
            for v in views}


def _cell_of(record: dict):
    """The :class:`benchmark.cell.Cell` of a record, or None when the record does not name one."""
    from benchmark.cell import Cell

    try:
        return Cell.from_dict(record)
    except (KeyError, TypeError, ValueError):
        return None


def attach_input_content(df, root: str | Path):
    """``df`` with a column ``input_content``: each ok cell's :func:`input_fingerprint`, read from ``root``'s data
    (None where the data folder is gone), and ``input_key``, its name in a reference file
    (``<scene>-<size>/<weather>``)."""
    from benchmark.cell import data_dir
    from benchmark.store import record_data_name

    df = df.copy()
    cache: dict[str, dict | None] = {}
    keys, contents = [], []
    for _, row in df.iterrows():
        rec = row.get("record")
        cell = _cell_of(rec) if isinstance(rec, dict) and row["status"] == "ok" else None
        if cell is None:
            keys.append(None)
            contents.append(None)
            continue
        key = f"{record_data_name(rec)}/{cell.weather}"  # refuses a scene or size that is not one name
        if key not in cache:
            cache[key] = input_fingerprint(data_dir(Path(root), cell))
        keys.append(key)
        contents.append(cache[key])
    df["input_key"] = keys
    df["input_content"] = contents
    return df


def input_change(got: dict, want: dict) -> tuple[float, str]:
    """Largest change of a recorded block mean between two :func:`input_fingerprint` results, 8-bit levels, and
    where it is (``inf`` when the views differ)."""
    if set(got) != set(want):
        missing, extra = sorted(set(want) - set(got)), sorted(set(got) - set(want))
        return float("inf"), f"views differ (missing {missing[:3]}, unexpected {extra[:3]})"
    worst, where = 0.0, ""
    for name in sorted(want):
        for kind in ("image", "clean"):
            a, b = decode_fingerprint(got[name][kind]), decode_fingerprint(want[name][kind])
            d = float(np.abs(a - b).max()) if a.shape == b.shape else float("inf")
            if d > worst:
                worst, where = d, f"{name} ({kind})"
    return worst, where


def _input_check(rec, ref: dict, reference: dict, tol: Tolerance) -> tuple[str, str | None]:
    """(diff-table word, problem or None) for one cell's synthesised input."""
    want = (reference.get("inputs") or {}).get(ref.get("input"))
    same_bytes = rec["input_sha256"] == ref.get("input_sha256")
    if want is None:  # a reference written before inputs were recorded by content
        return ("same" if same_bytes else "bytes differ"), None
    got = rec.get("input_content")
    if not isinstance(got, dict):
        return "unread!", (f"its synthesised input could not be read (data folder of {ref['input']} missing); "
                           "rerun the cell to compare it with the reference")
    change, where = input_change(got, want)
    # Both sides were rounded to 1/CONTENT_SCALE level when recorded.
    if change > tol.input_levels + 1.0 / CONTENT_SCALE:
        return "CHANGED!", (f"the synthesised input changed: {where} differs by {change:.2f} 8-bit levels "
                            f"(block means; tolerance {tol.input_levels})")
    if same_bytes:
        return "same", None
    return f"~{change:.2f}", None


def make_reference(df, tolerance: Tolerance = Tolerance(), grid: RegressionGrid | None = None) -> dict:
    """Reference figures (JSON-ready) from :func:`benchmark.store.load_results` output (ok cells only).

    With ``grid`` (the regression grid), every one of its cells must be ``ok`` (a failed cell
    would silently drop out of the check) and the grid is recorded in the file.
    """
    ok = df[df["status"] == "ok"].sort_values("cell_id")
    if len(ok) == 0:
        raise NimbusError("no finished cell in the store; run the benchmark before writing references")
    if grid is not None:
        failed = sorted({c.cell_id for c in grid.cells()} - set(ok["cell_id"]))
        if failed:
            raise NimbusError(f"{len(failed)} regression cell(s) did not finish ({', '.join(failed)}); fix them "
                              "before writing references")
    cells, inputs = {}, {}
    for _, r in ok.iterrows():
        cells[r["cell_id"]] = {"psnr": _round(r["psnr"], 4), "ssim": _round(r["ssim"], 5),
                               "lpips": _round(r["lpips"], 5), "input_sha256": r["input_sha256"],
                               "config_hash": r["config_hash"]}
        content = r.get("input_content")
        if isinstance(content, dict):
            cells[r["cell_id"]]["input"] = r["input_key"]
            inputs[r["input_key"]] = content
    protocol = sorted(set(ok["ssim_protocol"].dropna()))
    nets = sorted(set(ok["lpips_net"].dropna()))
    out = {"format": REFERENCE_FORMAT, "tolerance": asdict(tolerance), "ssim_protocol": protocol,
           "lpips_net": nets, "cells": cells}
    if inputs:
        out["inputs"] = inputs
        out["input_content"] = {"grid": list(CONTENT_GRID), "unit": f"1/{CONTENT_SCALE} of an 8-bit level",
                                "what": "per view: channel means (R, G, B) of each block, rows then columns, "
                                        "4 hex digits each, of the degraded image and of the clean image"}
    if grid is not None:
        out["grid"] = asdict(grid)
        out["update_command"] = "nimbus-bench reference update --regression"
    return out


def _round(v, n):
    return None if v is None or v != v else round(float(v), n)


def _missing(v) -> bool:
    return v is None or v != v


def compare(df, reference: dict) -> list[str]:
    """Problems (empty list: pass) of the store's cells against ``reference``."""
    tol = Tolerance(**reference.get("tolerance", {}))
    latest = {r["cell_id"]: r for _, r in df.iterrows()}
    problems = []
    for cid, ref in sorted(reference["cells"].items()):
        rec = latest.get(cid)
        if rec is None:
            problems.append(f"{cid}: not run")
            continue
        if rec["status"] != "ok":
            problems.append(f"{cid}: failed ({rec['error']})")
            continue
        _, problem = _input_check(rec, ref, reference, tol)
        if problem:
            problems.append(f"{cid}: {problem}")
        for key, field, sign in METRICS:
            want, got, limit = ref.get(key), rec[key], getattr(tol, field)
            if want is None:
                continue
            if _missing(got):
                problems.append(f"{cid}: {key} missing (reference {want})"
                                + ("; run `nimbus-bench setup-weights`" if key == "lpips" else ""))
            elif sign * (want - got) > limit:
                problems.append(f"{cid}: {key} {got:.4f} is worse than the reference {want:.4f} "
                                f"by more than {limit}")
    return problems


def notes(df, reference: dict) -> list[str]:
    """What passes but makes the references stale: figures better by more than the tolerance, changed configs."""
    tol = Tolerance(**reference.get("tolerance", {}))
    latest = {r["cell_id"]: r for _, r in df.iterrows()}
    out = []
    for cid, ref in sorted(reference["cells"].items()):
        rec = latest.get(cid)
        if rec is None or rec["status"] != "ok":
            continue
        better = [key for key, field, sign in METRICS if ref.get(key) is not None and not _missing(rec[key])
                  and sign * (rec[key] - ref[key]) > getattr(tol, field)]
        if better:
            out.append(f"{cid}: better than the reference ({', '.join(better)})")
        if ref.get("config_hash") and rec["config_hash"] != ref["config_hash"]:
            out.append(f"{cid}: the trainer config changed since the reference was written")
    return out


def diff_table(df, reference: dict) -> str:
    """One line per reference cell: each metric's reference, value now and change; ``!`` marks a regression."""
    tol = Tolerance(**reference.get("tolerance", {}))
    latest = {r["cell_id"]: r for _, r in df.iterrows()}
    width = max([len(c) for c in reference["cells"]] + [4])
    head = f"{'cell':<{width}}" + "".join(f"  {k.upper() + ' ref':>10} {'now':>8} {'change':>8} "
                                          for k, _, _ in METRICS)
    lines = [head + "  input", "-" * (len(head) + 7)]
    for cid, ref in sorted(reference["cells"].items()):
        rec = latest.get(cid)
        if rec is None or rec["status"] != "ok":
            lines.append(f"{cid:<{width}}  {'not run' if rec is None else 'FAILED: ' + str(rec['error'])}")
            continue
        row = f"{cid:<{width}}"
        for key, field, sign in METRICS:
            want, got = ref.get(key), rec[key]
            if want is None or _missing(got):
                row += f"  {'-' if want is None else want:>10} {'-' if _missing(got) else f'{got:.4f}':>8} {'':>8} "
                continue
            bad = sign * (want - got) > getattr(tol, field)
            row += f"  {want:>10.4f} {got:>8.4f} {got - want:>+8.4f}{'!' if bad else ' '}"
        row += "  " + _input_check(rec, ref, reference, tol)[0]
        lines.append(row)
    lines.append(f"tolerance: PSNR -{tol.psnr_db} dB, SSIM -{tol.ssim}, LPIPS +{tol.lpips}, "
                 f"input {tol.input_levels} 8-bit level(s)")
    lines.append("input: same = identical bytes; ~x = other bytes (another CPU, library or version), content "
                 "within x levels; CHANGED! = content beyond the tolerance")
    return "\n".join(lines)


def load_reference(path: str | Path) -> dict:
    """A reference file's contents (NimbusError when missing or not JSON)."""
    path = Path(path)
    if not path.is_file():
        raise NimbusError(f"reference file {path} does not exist; create it with "
                          f"`nimbus-bench reference update --regression` (or --root ROOT --reference {path})")
    try:
        reference = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise NimbusError(f"{path} is not valid JSON ({e.msg})") from None
    if reference.get("format") != REFERENCE_FORMAT or not isinstance(reference.get("cells"), dict):
        raise NimbusError(f"{path} is not a {REFERENCE_FORMAT} reference file")
    return reference
