"""``nimbus-bench stability``: extreme inputs through synthesis, training and scoring (:mod:`benchmark.stability`)."""

from __future__ import annotations

import argparse
import sys
import tempfile
import time

from benchmark.stability import (DEFAULT_ITERATIONS, DEFAULT_PRESET, DEFAULT_SCENE, DEFAULT_SIZE, OWNER,
                                 StabilityOptions, get_cases, run_report, to_markdown, write_report)
from nimbus.errors import NimbusError

HELP = "run extreme inputs (no / opaque haze, black / white images, one view, degenerate Gaussians) through " \
       "synthesis, training and scoring: outcome, NaNs, metrics, time"
EXAMPLE = "nimbus-bench stability --out stability/ --cases no_haze,white_inputs --methods 3dgs"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from nimbus.metrics import LPIPS_NETS, SSIM_PROTOCOLS

    p.add_argument("--out", default="stability", help="folder for stability.csv / .md / .json")
    p.add_argument("--cases", default="all", help="comma list of case names (see --list) or all")
    p.add_argument("--methods", default=None, help="run only these of each case's methods (comma list)")
    p.add_argument("--iterations", type=int, default=DEFAULT_ITERATIONS,
                   help="training iterations of every run (the preset's schedule is rescaled)")
    p.add_argument("--preset", default=DEFAULT_PRESET, help="trainer preset: tiny, fast, paper")
    p.add_argument("--scene", default=DEFAULT_SCENE, help="built-in scene the inputs are made from")
    p.add_argument("--size", default=DEFAULT_SIZE, help="built-in scene size: tiny, compact, small, standard")
    p.add_argument("--ssim", choices=tuple(SSIM_PROTOCOLS), default="3dgs", help="SSIM protocol (3dgs: paper)")
    p.add_argument("--lpips", choices=LPIPS_NETS + ("none",), default="vgg", help="LPIPS network (vgg: paper)")
    p.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    p.add_argument("--work", default=None, metavar="DIR",
                   help="keep the inputs and runs in DIR (default: a temporary folder, removed afterwards)")
    p.add_argument("--overwrite", action="store_true", help="replace this command's earlier --out folder (any other is refused)")
    p.add_argument("--list", action="store_true", help="describe the cases and exit")


def run(args: argparse.Namespace) -> int:
    from nimbus.data.builtin import get_scene, get_size
    from nimbus.methods.registry import get_method
    from nimbus.utils.fs import check_output_dir

    cases = get_cases(args.cases)
    if args.list:
        for c in cases:
            print(f"{c.name:<20} {c.description}\n{'':<20} input: {c.input_summary}; methods: {', '.join(c.methods)}; "
                  f"expected: {c.expect}")
        return 0
    check_output_dir(args.out, args.overwrite, owner=OWNER)  # before any work: a bad --out should not cost a run
    get_scene(args.scene)
    get_size(args.size)
    if args.iterations < 2:
        raise NimbusError(f"--iterations must be at least 2 (NimbusGS needs both stages), got {args.iterations}")
    methods = None
    if args.methods:
        methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
        for m in methods:
            get_method(m)
        if not any(m in c.methods for c in cases for m in methods):
            raise NimbusError(f"none of the selected cases runs {', '.join(methods)}; "
                              f"their methods are {', '.join(sorted({m for c in cases for m in c.methods}))}")
    for m in {m for c in cases for m in c.methods}:
        get_method(m).preset(args.preset)  # an unknown preset fails here, before any work
    options = StabilityOptions(args.scene, args.size, args.preset, args.iterations, methods, args.ssim,
                               None if args.lpips == "none" else args.lpips, args.device)
    t0 = time.perf_counter()
    if args.work:
        rows = run_report(cases, args.work, options)
    else:
        with tempfile.TemporaryDirectory(prefix="nimbus-stability-") as work:
            rows = run_report(cases, work, options)
    wall = time.perf_counter() - t0
    written = write_report(args.out, rows, cases, options, overwrite=args.overwrite, wall_s=wall)
    print(to_markdown(rows, cases, options, wall), end="")
    for path in written:
        print(path, file=sys.stderr)
    bad = [r for r in rows if r["verdict"] != "ok"]
    if bad:
        print(f"{len(bad)} run(s) failed the report: "
              + "; ".join(f"{r['case']} / {r['method']} ({r['verdict']})" for r in bad), file=sys.stderr)
        return 1
    return 0
