"""``nimbus-bench hostile``: faulty and malicious inputs through the real CLIs, sandboxed (:mod:`benchmark.hostile`)."""

from __future__ import annotations

import argparse

from benchmark.commands.case_report import add_report_arguments, list_cases, run_and_report
from benchmark.hostile import OWNER, make_removable, get_cases, run_report, to_markdown, write_report

HELP = "run hostile and faulty inputs through nimbus-synth / -train / -bench in sandboxes: outcome, inputs " \
       "modified, writes outside --out, partial output, time and memory"
EXAMPLE = "nimbus-bench hostile --out hostile/ --cases pickle_resume,points3d_count_2e60"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_report_arguments(p, "hostile", "hostile.md / hostile.csv", "sandboxes")


def run(args: argparse.Namespace) -> int:
    from nimbus.utils.fs import check_output_dir

    cases = get_cases(args.cases)
    if args.list:
        return list_cases(cases, 28, lambda c: f"expected: {c.expect}; {c.command}")
    check_output_dir(args.out, args.overwrite, owner=OWNER)  # before any work: a bad --out should not cost a run
    return run_and_report(
        args, "nimbus-hostile-", lambda work: run_report(cases, work),
        write=lambda rows, wall: write_report(args.out, rows, cases, overwrite=args.overwrite, wall_s=wall),
        markdown=lambda rows, wall: to_markdown(rows, cases, wall),
        failed=lambda bad: f"{len(bad)} case(s) failed the report: " + ", ".join(r["case"] for r in bad),
        cleanup=make_removable)  # a read-only --out case would stop the clean-up
