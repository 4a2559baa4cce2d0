"""CI regression check: compare a tiny benchmark's figures with committed reference figures.

``nimbus-bench reference check --root ROOT --reference FILE`` fails (exit 1) when a cell's
quality dropped by more than the tolerance (PSNR, SSIM lower; LPIPS higher), when its
synthesised input changed (the degraded dataset's manifest hash), or when a reference
cell is missing or failed.  ``nimbus-bench reference update`` rewrites FILE from the
store, so a deliberate change shows as a diff of the reference file in review.
"""

from __future__ import annotations

import argparse
import json
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

from nimbus.errors import NimbusError

REFERENCE_FORMAT = "nimbus-bench-reference/1"


@dataclass(frozen=True)
class Tolerance:
    """How much worse a figure may get before CI fails (run-to-run noise of the tiny preset on a CPU).

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


def make_reference(df, tolerance: Tolerance = Tolerance()) -> dict:
    """Reference figures (JSON-ready) from :func:`benchmark.store.load_results` output (ok cells only)."""
    ok = df[df["status"] == "ok"].sort_values("cell_id")
    if len(ok) == 0:
        raise NimbusError("no finished cell in the store; run the benchmark before writing references")
    cells = {}
    for _, r in ok.iterrows():
        cells[r["cell_id"]] = {"psnr": _round(r["psnr"], 4), "ssim": _round(r["ssim"], 5),
                               "lpips": _round(r["lpips"], 5), "input_sha256": r["input_sha256"],
                               "config_hash": r["config_hash"]}
    protocol = sorted(set(ok["ssim_protocol"].dropna()))
    nets = sorted(set(ok["lpips_net"].dropna()))
    return {"format": REFERENCE_FORMAT, "tolerance": asdict(tolerance), "ssim_protocol": protocol,
            "lpips_net": nets, "cells": cells}


def _round(v, n):
    return None if v is None or v != v else round(float(v), n)


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
            problems.append(f"{cid}: the synthesised input changed (manifest sha256 {rec['input_sha256'][:12]} "
                            f"!= {ref['input_sha256'][:12]})")
        for key, limit, sign in (("psnr", tol.psnr_db, 1), ("ssim", tol.ssim, 1), ("lpips", tol.lpips, -1)):
            want, got = ref.get(key), rec[key]
            if want is None:
                continue
            if got is None or got != got:
                problems.append(f"{cid}: {key} missing (reference {want})")
            elif sign * (want - got) > limit:
                problems.append(f"{cid}: {key} {got:.4f} is worse than the reference {want:.4f} "
                                f"by more than {limit}")
    return problems


# --- command line (``nimbus-bench reference``) -----------------------------------------------
HELP = "CI regression: check a benchmark store against committed reference figures, or update them"
EXAMPLE = "nimbus-bench reference check --root bench_ci --reference benchmark/reference_tiny.json"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=("check", "update"), help="check: compare and fail on regressions; "
                                                                 "update: rewrite the reference file")
    p.add_argument("--root", required=True, help="benchmark folder holding results.jsonl")
    p.add_argument("--reference", required=True, metavar="FILE", help="reference figures (JSON, committed)")


def run(args: argparse.Namespace) -> int:
    from benchmark.store import load_results, store_path
    from nimbus.utils.fs import atomic_write_text

    if not store_path(args.root).is_file():
        raise NimbusError(f"{store_path(args.root)} does not exist; run `nimbus-bench run --root {args.root}` first")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        df = load_results(args.root)
    ref_path = Path(args.reference)
    if args.action == "update":
        old = json.loads(ref_path.read_text()) if ref_path.is_file() else {}
        tol = Tolerance(**old.get("tolerance", {}))
        atomic_write_text(ref_path, json.dumps(make_reference(df, tol), indent=1, sort_keys=True) + "\n")
        print(f"wrote {ref_path}; review and commit its diff")
        return 0
    if not ref_path.is_file():
        raise NimbusError(f"reference file {ref_path} does not exist; create it with "
                          f"`nimbus-bench reference update --root {args.root} --reference {ref_path}`")
    try:
        reference = json.loads(ref_path.read_text())
    except json.JSONDecodeError as e:
        raise NimbusError(f"{ref_path} is not valid JSON ({e.msg})") from None
    problems = compare(df, reference)
    for p in problems:
        print(f"REGRESSION {p}")
    print(f"{len(reference['cells'])} reference cell(s) checked: "
          f"{'ok' if not problems else f'{len(problems)} problem(s)'}")
    return 1 if problems else 0
