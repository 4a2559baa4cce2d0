"""Write the paper-style tables from the results store (``nimbus-bench tables``).

Per-weather method comparisons (:mod:`benchmark.tables`), the ablation tables and the
complexity / runtime table (:mod:`benchmark.ablation_tables`), each with the paper's numbers
beside it where the paper has the layout.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

from nimbus.errors import NimbusError

HELP = ("write the paper-style tables (per-weather comparisons, ablations, complexity / runtime) as LaTeX, "
        "Markdown and CSV from the results store")
EXAMPLE = "nimbus-bench tables --root bench_runs --out tables/"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--root", default="bench_runs", help="benchmark folder holding results.jsonl")
    p.add_argument("--out", default="tables", help="folder to write the tables into")
    p.add_argument("--methods", default=None, help="row order: comma list of methods listed first")
    p.add_argument("--parquet", metavar="FILE", default=None, help="also export the store as Parquet")


def run(args: argparse.Namespace) -> int:
    from benchmark.ablation_tables import ablation_tables, write_ablation_tables
    from benchmark.grid import DEFAULT_METHODS
    from benchmark.store import export_parquet, load_results, store_path
    from benchmark.tables import Written, write_tables
    from nimbus.utils.fs import check_output_dir, refuse_overlap

    root, store = Path(args.root), store_path(args.root)
    try:
        if root.exists() and not root.is_dir():
            raise NimbusError(f"--root {root} is a file; give the benchmark folder that holds results.jsonl")
        if not store.is_file():
            raise NimbusError(f"{store} does not exist; run `nimbus-bench run --root {args.root}` first")
    except PermissionError:
        raise NimbusError(f"--root {root} cannot be read (permission denied); give read access or choose another "
                          "--root") from None
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
    order = [m.strip() for m in args.methods.split(",")] if args.methods else list(DEFAULT_METHODS)
    # Every table is computed before the first file is written, so a refused store writes nothing.
    ablations, skipped = ablation_tables(df, order)
    written = write_tables(df, args.out, order)
    written += write_ablation_tables(ablations, args.out)
    if args.parquet:
        written.append(Written(export_parquet(args.root, args.parquet), "the results store as Parquet"))
    width = max(len(str(w.path)) for w in written)
    for w in written:
        print(f"{str(Path(w.path)):<{width}}  {w.what}")
    if skipped:
        print(f"not written (no variant of theirs was run): {', '.join(skipped)}")
    return 0
