"""The hostile-input report: the robustness tests, run and tabulated by family.

Usage::

    python -m tools.hostile [--families data,train,synth,config,bench] [--quick] [PYTEST_ARG ...]

The hostile and faulty inputs of issue 14 (and later) are tests, one file per family,
``tests/test_hostile_<family>.py``: ``data`` (scene files: names that leave the scene, corrupt
COLMAP models, malformed JSON / PLY, bad depth maps, image bombs), ``train`` (checkpoints that
would run code, ``--out`` over the scene, unusable run folders), ``synth`` (``nimbus-synth``
writing only inside ``--out``, killed runs), ``config`` (out-of-range ``--set`` values, sizes
beyond the machine) and ``bench`` (two runs on one root, stores and reports that lead out).
Each test builds its hostile input and asserts the tool ends cleanly: one ``error:`` line and
exit 2 (or a finished run), nothing written outside ``--out``, no input changed, nothing partial
left.  This runs those files with pytest in a child process (``--junitxml``) and prints one
line per family through the table writer: cases run, cases that ended cleanly, and the holes
(failed or erroring cases), named under the table.  Exit status 1 when there is a hole, 2 for
an unknown family.  ``--quick`` leaves out the tests marked ``slow``; further arguments go to
pytest (``-k pickle``).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass, field
from pathlib import Path

from benchmark.tables.model import Block, Column, Row, Table
from benchmark.tables.writer import to_markdown
from nimbus.cli_util import run_cli
from nimbus.errors import NimbusError

TESTS = Path(__file__).resolve().parents[1] / "tests"
PREFIX = "test_hostile_"
GROUP = "all"
COLUMNS = (Column("cases", "cases", "cases"), Column("clean", "ended cleanly", "ended cleanly"),
           Column("holes", "holes", "holes"))


@dataclass
class Family:
    """One family's outcome: the cases run, those that passed, the node ids that failed or erred, skips."""

    name: str
    cases: int = 0
    clean: int = 0
    holes: list[str] = field(default_factory=list)
    skipped: int = 0


def families(tests: Path = TESTS) -> list[str]:
    """The families there are: ``tests/test_hostile_<family>.py``, in name order."""
    return sorted(p.stem[len(PREFIX):] for p in tests.glob(f"{PREFIX}*.py"))


def pick(spec: str | None, tests: Path = TESTS) -> list[str]:
    known = families(tests)
    if not spec or spec == "all":
        return known
    wanted = [s.strip() for s in spec.split(",") if s.strip()]
    unknown = [w for w in wanted if w not in known]
    if unknown:
        raise NimbusError(f"unknown hostile family {', '.join(map(repr, unknown))}; choose from {', '.join(known)}")
    return wanted


def tally(junit_xml: str, names: list[str]) -> list[Family]:
    """Per family (in ``names`` order), the cases of a pytest ``--junitxml`` report (our own child's file)."""
    out = {n: Family(n) for n in names}
    for case in ElementTree.parse(junit_xml).getroot().iter("testcase"):
        module = case.get("classname", "").split(".")
        stem = next((m for m in module if m.startswith(PREFIX)), "")
        fam = out.get(stem[len(PREFIX):])
        if fam is None:
            continue
        if case.find("skipped") is not None:
            fam.skipped += 1
            continue
        fam.cases += 1
        if case.find("failure") is None and case.find("error") is None:
            fam.clean += 1
        else:
            fam.holes.append(f"{stem}.py::{case.get('name')}")
    return [out[n] for n in names]


def run_families(names: list[str], pytest_args: list[str] = (), tests: Path = TESTS) -> list[Family]:
    """Run the families' test files in one pytest child and tally them."""
    with tempfile.TemporaryDirectory(prefix="nimbus-hostile-") as tmp:
        report = str(Path(tmp) / "junit.xml")
        files = [str(tests / f"{PREFIX}{n}.py") for n in names]
        subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={report}",
                        *files, *pytest_args], cwd=tests.parent, check=False)
        if not Path(report).is_file():
            raise NimbusError("pytest wrote no report (see its output above); is pytest installed (.[test])?")
        return tally(report, names)


def table(results: list[Family]) -> Table:
    """The family table: one row per family and a total; the holes and skips in the notes."""
    def row(label: str, fams: list[Family]) -> Row:
        return Row(label, {(GROUP, "cases"): sum(f.cases for f in fams), (GROUP, "clean"): sum(f.clean for f in fams),
                           (GROUP, "holes"): sum(len(f.holes) for f in fams)})

    notes = [f"Hole: {h}" for f in results for h in f.holes]
    skipped = sum(f.skipped for f in results)
    if skipped:
        notes.append(f"{skipped} case(s) skipped (not counted)")
    blocks = [Block([row(f.name, [f]) for f in results], ranked=False)]
    if len(results) > 1:
        blocks[0].rows.append(row("all", results))
        blocks[0].rows[-1].rule_before = True
    return Table("hostile", "hostile", "Hostile inputs by family", COLUMNS, [GROUP], blocks, lead=("family",),
                 notes=notes, group_heads=False)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.hostile", description=__doc__.split("\n")[0])
    parser.add_argument("--families", default="all", help="comma list of families (default: every "
                        "tests/test_hostile_<family>.py)")
    parser.add_argument("--quick", action="store_true", help="leave out the tests marked slow")
    args, rest = parser.parse_known_args(argv)
    names = pick(args.families)
    results = run_families(names, (["-m", "not slow"] if args.quick else []) + rest)
    print(to_markdown(table(results)), end="")
    return 1 if any(f.holes for f in results) else 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
