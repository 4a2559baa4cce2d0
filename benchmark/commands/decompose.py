"""``nimbus-bench decompose``: a medium-modelling run's learned T, airlight and clean render against the ground
truth the synthesiser kept, per depth band (:mod:`benchmark.decompose`, table :mod:`benchmark.tables.decompose`).

The run folder is only read; ``decompose.json`` (the record) and ``decompose.md`` (its table) go into
``--out`` (default ``RUN/decompose``), each written atomically.
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = ("check a NimbusGS / medium-3dgs run's decomposition against the synthesised layers: T, airlight and "
        "clean-render bias per depth band, and the PSNR a per-channel offset costs")
EXAMPLE = "nimbus-bench decompose bench_runs/runs/garden-tiny_H_nimbus_tiny_s0"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", metavar="RUN", help="a finished run folder of a method that models a medium, trained on "
                                              "a nimbus-synth setting folder (e.g. a nimbus-bench run cell)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="folder for decompose.json and decompose.md (default: RUN/decompose; the two files are "
                        "replaced, nothing else in it is touched)")
    p.add_argument("--device", default=None, help="torch device to render on (default: cuda if available, else cpu)")


def run(args: argparse.Namespace) -> int:
    from benchmark.decompose import DEFAULT_DIR, MARKDOWN, RECORD, decompose_run
    from benchmark.tables.decompose import decompose_table
    from benchmark.tables.writer import to_markdown
    from nimbus.cli.train import parse_device
    from nimbus.utils.fs import atomic_write_json, atomic_write_text, check_output_dir
    from nimbus.utils.jsonable import jsonable

    device = parse_device(args.device)
    out = Path(args.out) if args.out else Path(args.run) / DEFAULT_DIR
    check_output_dir(out, overwrite=True)  # before the model is loaded: a bad --out should cost nothing
    record = jsonable(decompose_run(args.run, device=device))
    text = to_markdown(decompose_table(record))  # made before either file is written
    print(text, end="")
    print(atomic_write_json(out / RECORD, record))
    print(atomic_write_text(out / MARKDOWN, text))
    return 0
