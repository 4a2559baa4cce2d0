"""``nimbus-bench compare``: two results stores, cell by cell (:mod:`benchmark.tables.agreement`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from benchmark.commands import METHODS_ORDER_HELP

HELP = ("compare two results stores on the cells both ran (another device, CPU, torch or code): each figure's "
        "difference, and whether the methods' order holds")
EXAMPLE = "nimbus-bench compare --root bench_cpu --against bench_cuda --names cpu,cuda --out compare/"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--root", required=True, help="store A: benchmark folder holding results.jsonl")
    p.add_argument("--against", required=True, help="store B: benchmark folder holding results.jsonl")
    p.add_argument("--names", default="A,B", help="the two stores' names in the table, A first")
    p.add_argument("--out", default=None,
                   help="folder for compare.md / .tex / .csv; without it only the summary is printed")
    p.add_argument("--methods", default=None, help=METHODS_ORDER_HELP)


def run(args: argparse.Namespace) -> int:
    import warnings

    from benchmark.grid import DEFAULT_METHODS
    from benchmark.store import load_results, require_store, split_method_labels
    from benchmark.tables.agreement import compare
    from benchmark.tables.writer import to_csv, to_latex, to_markdown
    from nimbus.errors import NimbusError
    from nimbus.utils.fs import atomic_write_text, check_output_dir

    names = tuple(n.strip() for n in args.names.split(","))
    if len(names) != 2 or not all(names) or names[0] == names[1]:
        raise NimbusError(f"--names {args.names!r}: give two different names, A's first (e.g. --names cpu,cuda)")
    stores = [require_store(args.root), require_store(args.against)]
    if stores[0].resolve() == stores[1].resolve():
        raise NimbusError(f"--root and --against are the same store ({stores[0]}); give two stores")
    if args.out:
        check_output_dir(args.out, overwrite=True, inputs=stores, flag="--out")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        frames = [load_results(args.root), load_results(args.against)]
    order = split_method_labels(args.methods) if args.methods else list(DEFAULT_METHODS)
    table, lines = compare(*frames, names=names, method_order=order)
    for line in lines:
        print(line)
    if args.out:
        texts = {f"{table.key}.md": to_markdown(table), f"{table.key}.tex": to_latex(table),
                 table.csv.name: to_csv([table])}  # all made before the first is written
        for name, text in texts.items():
            print(atomic_write_text(Path(args.out) / name, text))
    return 0
