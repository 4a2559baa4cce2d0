"""Write the paper-style tables from the results store (``nimbus-bench tables``).

Each layout (:data:`LAYOUTS`) builds its tables from the store, ours then the paper's numbers
beside them where the paper has the layout; :mod:`benchmark.tables.writer` renders them all.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path
from typing import Callable, NamedTuple

from benchmark.commands import METHODS_ORDER_HELP
from benchmark.tables import ablation, comparison, margins, provenance, runtime
from benchmark.tables.model import Combined, Table
from nimbus.errors import NimbusError

COMPARISONS = Combined("comparisons.md", "all method comparisons (ours, then the paper's)")
ABLATIONS = Combined("ablations.md", "all ablation and runtime tables (ours, then the paper's)")


class Layout(NamedTuple):
    """A table layout, as :data:`LAYOUTS` lists it.

    Attributes
    ----------
    tables : callable
        ``tables(df, method_order) -> (tables, skipped)``: our :class:`~benchmark.tables.model.Table`
        list from the store (``df``: :func:`benchmark.store.load_results` output; ``method_order``:
        methods listed first), and the layouts not written, as ``"<stem> (<paper label>)"``.
        Raises NimbusError when the store cannot make a table (empty, mixed protocols).
    paper : callable
        ``paper() -> {layout: table}``: the paper's numbers in the same layout (package data).
    markdown : Combined
        The Markdown file that gathers the tables (ours, each layout's followed by the paper's).
    """

    tables: Callable[..., tuple[list[Table], list[str]]]
    paper: Callable[[], dict[str, Table]]
    markdown: Combined


#: Every layout, in the order its files are written and listed.
LAYOUTS = (
    Layout(comparison.tables, comparison.paper, COMPARISONS),
    Layout(margins.tables, margins.paper, COMPARISONS),
    Layout(provenance.tables, provenance.paper, COMPARISONS),
    Layout(ablation.tables, ablation.paper, ABLATIONS),
    Layout(runtime.tables, runtime.paper, ABLATIONS),
)

HELP = ("write the paper-style tables (per-weather comparisons, ablations, complexity / runtime) as LaTeX, "
        "Markdown and CSV from the results store")
EXAMPLE = "nimbus-bench tables --root bench_runs --out tables/"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--root", default="bench_runs", help="benchmark folder holding results.jsonl")
    p.add_argument("--out", default="tables", help="folder to write the tables into")
    p.add_argument("--methods", default=None, help=METHODS_ORDER_HELP)
    p.add_argument("--parquet", metavar="FILE", default=None, help="also export the store as Parquet")


def run(args: argparse.Namespace) -> int:
    from benchmark.grid import DEFAULT_METHODS
    from benchmark.store import export_parquet, load_results, require_store, split_method_labels
    from benchmark.tables.writer import Written, with_paper, write_tables
    from nimbus.utils.fs import check_output_dir, refuse_overlap

    store = require_store(args.root)
    # The tables fill --out file by file (other files there stay), so a used folder is fine; but
    # it must be writable, and neither it nor --parquet may be or hold the store they are made from.
    check_output_dir(args.out, overwrite=True, inputs=[store], flag="--out")
    if args.parquet:
        refuse_overlap(args.parquet, [store], "--parquet")
        check_output_dir(Path(args.parquet).parent, overwrite=True, flag="--parquet")
        if Path(args.parquet).is_dir():
            raise NimbusError(f"--parquet {args.parquet} is a folder; give a file name such as results.parquet")
    with warnings.catch_warnings():  # a truncated last line is reported once, below
        warnings.simplefilter("ignore", UserWarning)
        df = load_results(args.root)
    order = split_method_labels(args.methods) if args.methods else list(DEFAULT_METHODS)
    if args.methods:  # a misspelt name would only move no row: say so
        known = set(df["method"].dropna())
        unknown = [m for m in order if m not in known]
        if unknown:
            print(f"--methods: the store has no method named {', '.join(unknown)}; it orders no row "
                  f"(methods there: {', '.join(sorted(known))})", file=sys.stderr)
    # Every table is computed before the first file is written, so a refused store writes nothing.
    sets, skipped = [], []
    for layout in LAYOUTS:
        ours, missing = layout.tables(df, order)
        sets.append((layout.markdown, with_paper(ours, layout.paper())))
        skipped += missing
    written = write_tables(sets, args.out)
    if args.parquet:
        written.append(Written(export_parquet(args.root, args.parquet), "the results store as Parquet"))
    width = max(len(str(w.path)) for w in written)
    for w in written:
        print(f"{str(Path(w.path)):<{width}}  {w.what}")
    if skipped:
        print(f"not written (nothing in the store to fill them): {', '.join(skipped)}")
    return 0
