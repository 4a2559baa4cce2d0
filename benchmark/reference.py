"""CI regression check: compare a tiny benchmark's figures with committed reference figures.

``nimbus-bench reference check --root ROOT --reference FILE`` fails (exit 1) when a cell's
quality dropped by more than the tolerance (PSNR, SSIM lower; LPIPS higher), when its
synthesised input changed (the degraded dataset's manifest hash), or when a reference
cell is missing or failed.  ``nimbus-bench reference update`` rewrites FILE from the
store, so a deliberate change shows as a diff of the reference file in review.

The regression grid
    :data:`REGRESSION_GRID` is the tiny benchmark CI runs (``tests/test_regression.py``,
    inside the README's ``python -m pytest``) against :data:`REGRESSION_REFERENCE`
    (``tables/reference/regression_tiny.json``).  ``nimbus-bench reference update
    --regression`` runs exactly that grid in a temporary folder and rewrites the file;
    ``check --regression`` runs it and checks, as the test does.

Determinism
    Scenes, synthesis and training seeds are fixed and the grid runs on the CPU with a
    fixed number of torch threads, so two runs on one machine give the same figures bit
    for bit.  The thread count is pinned because it matters: 1 instead of 2 threads
    changes the last bits of some kernels, which training amplifies (measured: up to
    0.17 dB PSNR / 0.004 LPIPS on one NimbusGS cell, < 4e-4 on the others).  The
    tolerance (:class:`Tolerance`) covers such differences between machines of one
    kind; a deliberate change to training or synthesis is expected to move the figures
    by more and is recorded with ``update``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from nimbus.errors import NimbusError

REFERENCE_FORMAT = "nimbus-bench-reference/1"
#: The committed reference figures of :data:`REGRESSION_GRID`.
REGRESSION_REFERENCE = Path(__file__).resolve().parents[1] / "tables" / "reference" / "regression_tiny.json"
#: Metric key, :class:`Tolerance` field, +1 when higher is better (-1: lower is better).
METRICS = (("psnr", "psnr_db", 1), ("ssim", "ssim", 1), ("lpips", "lpips", -1))


@dataclass(frozen=True)
class Tolerance:
    """How much worse a figure may get before the check fails.

    Stored in the reference file (these defaults apply when a new file is written).  On the
    tiny regression grid, runs on one machine repeat bit for bit, 1 vs 2 threads moved
    PSNR by up to 0.17 dB and LPIPS by 0.004, and a different training seed moves PSNR
    by 0.02-1 dB.

    Attributes
    ----------
    psnr_db : float
        Allowed PSNR drop, dB.
    ssim : float
        Allowed SSIM drop.
    lpips : float
        Allowed LPIPS rise.
    """

    psnr_db: float = 0.3
    ssim: float = 0.01
    lpips: float = 0.01


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
        """The grid's :class:`benchmark.grid.Cell` list, in table order."""
        from benchmark.grid import build_cells

        return build_cells(self.scenes, self.weathers, self.methods, [self.preset], self.seeds, self.size)

    def options(self):
        """The :class:`benchmark.grid.CellOptions` its cells run with."""
        from benchmark.grid import CellOptions

        return CellOptions(self.ssim_protocol, self.lpips_net, self.threads, self.device)


REGRESSION_GRID = RegressionGrid()


def run_regression(root: str | Path, grid: RegressionGrid = REGRESSION_GRID,
                   log: Callable[[str], None] | None = None):
    """Run every cell of ``grid`` afresh into ``root`` and return their records (:func:`load_results` rows).

    The cells run one after the other in one worker process (its own torch threads and
    state, whatever the caller's), always anew: a stale record in ``root`` is never reused.
    """
    from benchmark.grid import LocalExecutor, run_grid
    from benchmark.store import load_results

    cells = grid.cells()
    run_grid(cells, root, LocalExecutor(1, fresh_process=False), grid.options(), rerun=True, progress=False,
             log=log or (lambda s: None))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        df = load_results(root)
    return df[df["cell_id"].isin({c.cell_id for c in cells})]


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
    cells = {}
    for _, r in ok.iterrows():
        cells[r["cell_id"]] = {"psnr": _round(r["psnr"], 4), "ssim": _round(r["ssim"], 5),
                               "lpips": _round(r["lpips"], 5), "input_sha256": r["input_sha256"],
                               "config_hash": r["config_hash"]}
    protocol = sorted(set(ok["ssim_protocol"].dropna()))
    nets = sorted(set(ok["lpips_net"].dropna()))
    out = {"format": REFERENCE_FORMAT, "tolerance": asdict(tolerance), "ssim_protocol": protocol,
           "lpips_net": nets, "cells": cells}
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
        if rec["input_sha256"] != ref["input_sha256"]:
            problems.append(f"{cid}: the synthesised input changed (manifest sha256 {str(rec['input_sha256'])[:12]} "
                            f"!= {ref['input_sha256'][:12]})")
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
        row += "  same" if rec["input_sha256"] == ref["input_sha256"] else "  CHANGED!"
        lines.append(row)
    lines.append(f"tolerance: PSNR -{tol.psnr_db} dB, SSIM -{tol.ssim}, LPIPS +{tol.lpips}")
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


# --- command line (``nimbus-bench reference``) -----------------------------------------------
HELP = "CI regression: check a benchmark store against committed reference figures, or update them"
EXAMPLE = "nimbus-bench reference update --regression   # rerun the CI grid and rewrite its reference file"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=("check", "update"), help="check: compare and fail on regressions; "
                                                                 "update: rewrite the reference file")
    p.add_argument("--regression", action="store_true",
                   help="run the CI regression grid first (into --root, default a temporary folder) and use "
                        f"its reference file ({REGRESSION_REFERENCE.relative_to(REGRESSION_REFERENCE.parents[2])})")
    p.add_argument("--root", default=None, help="benchmark folder holding results.jsonl (required without "
                                                "--regression)")
    p.add_argument("--reference", default=None, metavar="FILE",
                   help="reference figures (JSON, committed); default with --regression: the CI grid's file")


def run(args: argparse.Namespace) -> int:
    from benchmark.store import load_results, store_path
    from nimbus.utils.fs import atomic_write_text

    if args.regression:
        ref_path = Path(args.reference) if args.reference else REGRESSION_REFERENCE
        if args.action == "check":
            reference = load_reference(ref_path)  # before the run: a missing file fails at once
        print(f"running the regression grid: {len(REGRESSION_GRID.cells())} cells", flush=True)
        with tempfile.TemporaryDirectory(prefix="nimbus-regression-") as tmp:
            df = run_regression(args.root or tmp, log=print)
    else:
        if args.root is None or args.reference is None:
            raise NimbusError("give --root ROOT and --reference FILE, or --regression for the CI grid")
        if not store_path(args.root).is_file():
            raise NimbusError(f"{store_path(args.root)} does not exist; run `nimbus-bench run --root {args.root}` "
                              "first")
        ref_path = Path(args.reference)
        if args.action == "check":
            reference = load_reference(ref_path)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            df = load_results(args.root)
    if args.action == "update":
        old = json.loads(ref_path.read_text()) if ref_path.is_file() else {}
        tol = Tolerance(**old.get("tolerance", {}))
        new = make_reference(df, tol, REGRESSION_GRID if args.regression else None)
        atomic_write_text(ref_path, json.dumps(new, indent=1, sort_keys=True) + "\n")
        if old.get("cells"):
            print(diff_table(df, old))
        print(f"wrote {ref_path} ({len(new['cells'])} cells); review and commit its diff")
        return 0
    print(diff_table(df, reference))
    for n in notes(df, reference):
        print(f"note: {n} (update the references with `nimbus-bench reference update`)")
    problems = compare(df, reference)
    for p in problems:
        print(f"REGRESSION {p}")
    print(f"{len(reference['cells'])} reference cell(s) checked: "
          f"{'ok' if not problems else f'{len(problems)} problem(s)'}")
    return 1 if problems else 0
