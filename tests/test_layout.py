"""The package layout: no import cycles, and imports go one way (benchmark -> weather_synth -> nimbus).

The import graph is read from the source with :mod:`ast` (nothing is imported), counting every
``import`` statement, also those inside functions: a lazy import hides a cycle from Python's
import machinery, not from a reader.
"""

from __future__ import annotations

import ast
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("nimbus", "weather_synth", "benchmark", "tools")
#: Which packages each may import (the direction of the layers); ``tools`` (not installed) is never imported by them.
ALLOWED = {"nimbus": {"nimbus"}, "weather_synth": {"weather_synth", "nimbus"},
           "benchmark": {"benchmark", "weather_synth", "nimbus"},
           "tools": {"tools", "benchmark", "weather_synth", "nimbus"}}


def modules(root: Path, packages=PACKAGES) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` under the packages (a package is its ``__init__``)."""
    out = {}
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def import_graph(root: Path, packages=PACKAGES) -> dict[str, set[str]]:
    """Module -> the project modules it imports (``from a.b import c`` counts ``a.b.c`` if that is a module)."""
    mods = modules(root, packages)
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[:len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            else:
                continue
            for target in targets:
                while target and target not in mods:  # a name inside a module -> that module
                    target = target.rpartition(".")[0]
                if target and target != name:
                    graph[name].add(target)
    return graph


def cycles(graph: dict[str, set[str]], ignore=frozenset()) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if (v, w) in ignore:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


@pytest.fixture(scope="module")
def graph():
    return import_graph(ROOT)


def test_no_import_cycles(graph):
    assert len(graph) > 100  # the whole tree was read
    assert cycles(graph) == []


def test_imports_go_one_way(graph):
    wrong = sorted((m, t) for m, targets in graph.items() for t in targets
                   if t.split(".")[0] not in ALLOWED[m.split(".")[0]])
    assert wrong == []


def installed_packages(root: Path) -> list[str]:
    """The packages the wheel ships: setuptools' ``find_packages`` with pyproject.toml's ``include`` patterns."""
    from setuptools import find_packages

    tomllib = pytest.importorskip("tomllib")  # Python 3.11+

    find = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    return sorted(find_packages(where=str(root), include=find["include"], exclude=find.get("exclude", ())))


def test_the_wheel_ships_the_three_packages_and_not_tools():
    shipped = installed_packages(ROOT)
    assert {"nimbus", "weather_synth", "benchmark", "benchmark.commands", "benchmark.tables"} <= set(shipped)
    assert [p for p in shipped if p.split(".")[0] not in {"nimbus", "weather_synth", "benchmark"}] == []
    # and what moved to tools/ left benchmark/ (a stale copy there would ship again)
    assert not any(p.startswith("benchmark.speed") for p in shipped)
    assert not (ROOT / "benchmark" / "gpu_check.py").exists()


def test_the_report_templates_ship_as_package_data():
    import fnmatch

    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["benchmark"]
    files = [p.relative_to(ROOT / "benchmark").as_posix() for p in (ROOT / "benchmark" / "templates").rglob("*")
             if p.is_file()]
    assert "templates/report.html" in files and "templates/table.html" in files
    assert [f for f in files if not any(fnmatch.fnmatch(f, pat) for pat in declared)] == []


def test_the_wheel_check_can_fail(tmp_path):
    for pkg in ("nimbus", "tools", "tools/speed"):
        (tmp_path / pkg).mkdir(parents=True)
        (tmp_path / pkg / "__init__.py").write_text("")
    (tmp_path / "pyproject.toml").write_text('[tool.setuptools.packages.find]\ninclude = ["nimbus*", "tools*"]\n')
    assert installed_packages(tmp_path) == ["nimbus", "tools", "tools.speed"]


def test_the_checks_can_fail(tmp_path):
    for name, text in {"nimbus/__init__.py": "", "nimbus/a.py": "from nimbus.b import f\n",
                       "nimbus/b.py": "def f():\n    from . import c\n", "nimbus/c.py": "import nimbus.a\n",
                       "nimbus/d.py": "from nimbus import a\nfrom weather_synth.x import y\n",
                       "weather_synth/__init__.py": "", "weather_synth/x.py": "y = 1\n"}.items():
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text(text)
    graph = import_graph(tmp_path, ("nimbus", "weather_synth"))
    assert cycles(graph) == [["nimbus.a", "nimbus.b", "nimbus.c"]]  # through a lazy, relative import
    assert graph["nimbus.d"] == {"nimbus.a", "weather_synth.x"}  # a back-edge the direction test refuses
    assert cycles(graph, {("nimbus.c", "nimbus.a")}) == []


def test_importing_the_library_changes_no_environment_variable_and_the_tools_set_the_openmp_policy():
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    # OpenCV's own loader adds to LD_LIBRARY_PATH when cv2 is imported: not ours, so it is loaded before the snapshot.
    check = ("import os, sys, cv2; before = dict(os.environ); import {mods}; "
             "sys.stdout.write(repr(sorted(set(os.environ.items()) ^ set(before.items()))))")
    lib = subprocess.run([sys.executable, "-c", check.format(mods="nimbus, nimbus.data, weather_synth, benchmark")],
                         env=env, capture_output=True, text=True, check=True)
    assert lib.stdout == "[]"
    for cli in ("nimbus.cli.train", "nimbus.cli.view", "weather_synth.cli", "benchmark.cli"):
        out = subprocess.run([sys.executable, "-c", check.format(mods=cli)], env=env, capture_output=True,
                             text=True, check=True)
        # The short spin is added only on an idle machine, which this one may or may not be now.
        assert out.stdout in ("[('OMP_WAIT_POLICY', 'PASSIVE')]",
                              "[('GOMP_SPINCOUNT', '1000'), ('OMP_WAIT_POLICY', 'PASSIVE')]"), (cli, out.stdout)
    # A spin count the user chose is kept; a policy the user chose adds nothing.
    for mine, want in (({"OMP_WAIT_POLICY": "ACTIVE"}, "[]"),
                       ({"GOMP_SPINCOUNT": "0"}, "[('OMP_WAIT_POLICY', 'PASSIVE')]")):
        out = subprocess.run([sys.executable, "-c", check.format(mods="benchmark.cli")], env={**env, **mine},
                             capture_output=True, text=True, check=True)
        assert out.stdout == want, (mine, out.stdout)


def test_the_tools_spin_briefly_only_on_an_idle_machine_and_never_over_the_users_choice():
    from nimbus.cli import IDLE_CORES, SPIN_COUNT, openmp_environment, other_processes_busy_cores

    passive = {"OMP_WAIT_POLICY": "PASSIVE"}
    assert openmp_environment({}, lambda: 0.0) == {**passive, "GOMP_SPINCOUNT": str(SPIN_COUNT)}
    assert openmp_environment({}, lambda: IDLE_CORES - 0.1)["GOMP_SPINCOUNT"] == "1000"
    for busy in (IDLE_CORES, 1.0, 7.5, None):  # at the threshold, a busy process beside, a loaded server, unknown
        assert openmp_environment({}, lambda: busy) == passive

    def unmeasured():
        raise AssertionError("measured the machine although the user chose")

    assert openmp_environment({"OMP_WAIT_POLICY": "ACTIVE"}, unmeasured) == {}
    assert openmp_environment({"OMP_WAIT_POLICY": "PASSIVE"}, unmeasured) == {}
    assert openmp_environment({"GOMP_SPINCOUNT": "0"}, unmeasured) == passive
    # The measurement itself: a share of the machine's cores, or None where /proc cannot be read.
    busy = other_processes_busy_cores(0.05)
    assert busy is None or 0.0 <= busy <= os.cpu_count() + 1
