"""``nimbus-bench reference``: check a benchmark store against committed reference figures, or update them
(:mod:`benchmark.reference`)."""

from __future__ import annotations

import argparse
import json
import tempfile
import warnings
from pathlib import Path

from benchmark.data import REGRESSION_REFERENCE
from benchmark.reference import (CROSS_CPU_TOLERANCE, EMULATED_CPUS, REGRESSION_GRID, Tolerance, attach_input_content,
                                 compare, diff_table, load_reference, make_reference, notes, run_regression)
from nimbus.errors import NimbusError

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
    p.add_argument("--emulate-cpu", choices=sorted(EMULATED_CPUS), default=None,
                   help="with --regression: run the grid in a child process whose libraries take the code paths "
                        "of an AVX2-only (avx2) or pre-AVX (generic) x86-64 CPU (how the tolerances were measured)")


def _run_emulated(args: argparse.Namespace) -> int:
    """Rerun this command in a child process with :data:`EMULATED_CPUS` ``[args.emulate_cpu]`` set (the
    libraries read their dispatch switches when they load)."""
    import os
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "benchmark.cli", "reference", args.action, "--regression",
           "--emulate-cpu", args.emulate_cpu]
    for flag, value in (("--root", args.root), ("--reference", args.reference)):
        if value is not None:
            cmd += [flag, str(value)]
    env = {**os.environ, **EMULATED_CPUS[args.emulate_cpu], _EMULATED_MARK: args.emulate_cpu}
    print(f"emulating CPU {args.emulate_cpu!r}: " + " ".join(f"{k}={v}" for k, v in
                                                          EMULATED_CPUS[args.emulate_cpu].items()), flush=True)
    return subprocess.run(cmd, env=env, check=False).returncode


# Set in the child of --emulate-cpu, so that it runs the grid instead of starting another child.
_EMULATED_MARK = "NIMBUS_EMULATED_CPU"


def run(args: argparse.Namespace) -> int:
    import os

    from benchmark.store import load_results, require_store
    from nimbus.utils.fs import atomic_write_text

    if args.emulate_cpu is not None:
        if not args.regression:
            raise NimbusError("--emulate-cpu applies to the regression grid; add --regression")
        if os.environ.get(_EMULATED_MARK) != args.emulate_cpu:
            return _run_emulated(args)
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
        require_store(args.root)
        ref_path = Path(args.reference)
        if args.action == "check":
            reference = load_reference(ref_path)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            df = load_results(args.root)
        df = attach_input_content(df, args.root)
    if args.action == "update":
        old = json.loads(ref_path.read_text()) if ref_path.is_file() else {}
        default = CROSS_CPU_TOLERANCE if args.regression else Tolerance()
        tol = Tolerance(**old["tolerance"]) if old.get("tolerance") else default
        new = make_reference(df, tol, REGRESSION_GRID if args.regression else None)
        if "cross_cpu_spread" in old:  # measured by hand (README), kept until measured again
            new["cross_cpu_spread"] = old["cross_cpu_spread"]
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
