"""``nimbus-bench report``: one static HTML page of a results store (:mod:`benchmark.html_report`)."""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from benchmark.commands import METHODS_ORDER_HELP
from benchmark.html_report import DEFAULT_VIEWS, THUMB_WIDTH

HELP = ("write an HTML report of the results store: summary table, test views of every method side by side, "
        "NimbusGS decompositions, trade-off / stability, provenance (one page + thumbnails, opens from disk)")
EXAMPLE = "nimbus-bench report --root bench_runs --out report/"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--root", default="bench_runs", help="benchmark folder holding results.jsonl")
    p.add_argument("--out", default="report", help="folder for index.html and images/ (replaced as a whole)")
    p.add_argument("--overwrite", action="store_true", help="replace an earlier report in --out (a folder this command wrote; any other is refused)")
    p.add_argument("--views", type=int, default=DEFAULT_VIEWS, help="test views shown per scene and setting")
    p.add_argument("--thumb-width", type=int, default=THUMB_WIDTH, help="largest thumbnail width in pixels")
    p.add_argument("--copy-full", action="store_true",
                   help="copy the full-size images into --out (portable, larger) instead of linking into the store")
    p.add_argument("--methods", default=None, help=METHODS_ORDER_HELP + " (default: nimbus, 3dgs)")
    p.add_argument("--tradeoff", default=None, metavar="DIR",
                   help="folder of `nimbus-bench tradeoff` outputs (default: looked for in ROOT and ROOT/*)")
    p.add_argument("--stability", default=None, metavar="DIR",
                   help="folder of `nimbus-bench stability` outputs (default: looked for in ROOT and ROOT/*)")


def run(args: argparse.Namespace) -> int:
    from benchmark.grid import DEFAULT_METHODS
    from benchmark.html_report import ReportOptions, build_report
    from benchmark.store import split_method_labels

    order = split_method_labels(args.methods) if args.methods else list(DEFAULT_METHODS)
    options = ReportOptions(views=args.views, thumb_width=args.thumb_width, copy_full=args.copy_full,
                            tradeoff=Path(args.tradeoff) if args.tradeoff else None,
                            stability=Path(args.stability) if args.stability else None, method_order=tuple(order))
    argv = ["nimbus-bench", "report", "--root", args.root, "--out", args.out]
    for flag, value, default in (("--views", args.views, DEFAULT_VIEWS), ("--thumb-width", args.thumb_width,
                                 THUMB_WIDTH), ("--methods", args.methods, None), ("--tradeoff", args.tradeoff, None),
                                 ("--stability", args.stability, None)):
        if value != default:
            argv += [flag, str(value)]
    argv += ["--copy-full"] * args.copy_full + ["--overwrite"] * args.overwrite
    page = build_report(args.root, args.out, options, command=shlex.join(argv), overwrite=args.overwrite)
    size = sum(f.stat().st_size for f in Path(args.out).rglob("*") if f.is_file())
    print(f"{page}  ({size / 1e6:.1f} MB with its images); open it in a browser")
    return 0
