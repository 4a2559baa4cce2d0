"""The command-line frame of a case report (``nimbus-bench stability``); not a verb.

A case report runs a list of named cases in scratch folders and write a report folder: the same
``--out`` / ``--cases`` / ``--work`` / ``--overwrite`` / ``--list`` flags, the same way of
listing the cases, of running them in a kept or temporary work folder, and of printing
the report and its files.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Sequence


def add_report_arguments(p: argparse.ArgumentParser, out: str, files: str, kept: str,
                         more: Callable[[argparse.ArgumentParser], None] | None = None) -> None:
    """``--out`` (default ``out``, a folder for ``files``) and ``--cases``, then ``more(p)``'s flags, then
    ``--work`` (where the ``kept`` scratch files stay), ``--overwrite`` and ``--list``."""
    p.add_argument("--out", default=out, help=f"folder for {files}")
    p.add_argument("--cases", default="all", help="comma list of case names (see --list) or all")
    if more is not None:
        more(p)
    p.add_argument("--work", default=None, metavar="DIR",
                   help=f"keep the {kept} in DIR (default: a temporary folder, removed afterwards)")
    p.add_argument("--overwrite", action="store_true", help="replace this command's earlier --out folder (any other is refused)")
    p.add_argument("--list", action="store_true", help="describe the cases and exit")


def list_cases(cases: Sequence, width: int, details: Callable[[object], str]) -> int:
    """Print each case's name and description, and ``details(case)`` on the line below (``--list``)."""
    for c in cases:
        print(f"{c.name:<{width}} {c.description}\n{'':<{width}} {details(c)}")
    return 0


def run_and_report(args: argparse.Namespace, prefix: str, run_cases: Callable[[str], list[dict]],
                   write: Callable[[list[dict], float], list[Path]], markdown: Callable[[list[dict], float], str],
                   failed: Callable[[list[dict]], str], cleanup: Callable[[Path], None] | None = None) -> int:
    """Run the cases in ``args.work`` (or a temporary folder named ``prefix...``), write and print the report.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed :func:`add_report_arguments` flags (``work`` is used here).
    prefix : str
        Prefix of the temporary work folder, used when ``--work`` is not given.
    run_cases : callable
        ``run_cases(work) -> rows``: runs every case with its scratch files under ``work``.
    write : callable
        ``write(rows, wall_s) -> paths``: writes the report into ``--out``.
    markdown : callable
        ``markdown(rows, wall_s) -> str``: the report printed on stdout.
    failed : callable
        ``failed(failed_rows) -> str``: the stderr line naming the rows whose verdict is not ``ok``.
    cleanup : callable, optional
        ``cleanup(work)`` before the temporary folder is removed (even when a case raised).

    Returns
    -------
    int
        The exit status: 1 when any row failed, else 0.
    """
    t0 = time.perf_counter()
    if args.work:
        rows = run_cases(args.work)
    else:
        with tempfile.TemporaryDirectory(prefix=prefix) as work:
            try:
                rows = run_cases(work)
            finally:
                if cleanup is not None:
                    cleanup(Path(work))
    wall = time.perf_counter() - t0
    written = write(rows, wall)
    print(markdown(rows, wall), end="")
    for p in written:
        print(p, file=sys.stderr)
    bad = [r for r in rows if r["verdict"] != "ok"]
    if bad:
        print(failed(bad), file=sys.stderr)
        return 1
    return 0
