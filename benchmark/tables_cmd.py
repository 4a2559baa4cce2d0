"""Write the per-weather comparison tables from the results store (``nimbus-bench tables``)."""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

from nimbus.errors import NimbusError

HELP = "write the paper-style per-weather comparison tables (LaTeX, Markdown, CSV) from the results store"
EXAMPLE = "nimbus-bench tables --root bench_runs --out tables/"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--root", default="bench_runs", help="benchmark folder holding results.jsonl")
    p.add_argument("--out", default="tables", help="folder to write the tables into")
    p.add_argument("--methods", default=None, help="row order: comma list of methods listed first")
    p.add_argument("--parquet", metavar="FILE", default=None, help="also export the store as Parquet")


def run(args: argparse.Namespace) -> int:
    from benchmark.grid import DEFAULT_METHODS
    from benchmark.store import export_parquet, load_results, store_path
    from benchmark.tables import write_tables

    if not store_path(args.root).is_file():
        raise NimbusError(f"{store_path(args.root)} does not exist; run `nimbus-bench run --root {args.root}` first")
    with warnings.catch_warnings():  # a truncated last line is reported once, below
        warnings.simplefilter("ignore", UserWarning)
        df = load_results(args.root)
    order = [m.strip() for m in args.methods.split(",")] if args.methods else list(DEFAULT_METHODS)
    written = write_tables(df, args.out, order)
    if args.parquet:
        written.append(export_parquet(args.root, args.parquet))
    for p in written:
        print(Path(p))
    return 0
