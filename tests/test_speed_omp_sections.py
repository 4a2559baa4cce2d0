"""tools.speed.omp_sections counts libgomp's parallel sections and names the torch operations that open them."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

from tools.speed import omp_sections

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux") or shutil.which("cc") is None,
                                reason="needs Linux and a C compiler")

CHILD = """
import ctypes, os, sys, torch
from tools.speed.omp_sections import SHIM_ENV, count_sections
torch.set_num_threads(int(sys.argv[1]))
shim = ctypes.CDLL(os.environ[SHIM_ENV])
x = torch.ones(1_000_000)
total, by_op = count_sections(shim, lambda: x.exp())
untouched = shim.omp_sections_total()
x.exp()
outside = shim.omp_sections_total() - untouched  # after the counted block: not counted
print(total, outside, sum(by_op.values()), sorted({op for (op, _) in by_op}))
"""


def _child(tmp_path, threads: int) -> str:
    lib = omp_sections.build_shim(tmp_path)
    env = {**os.environ, omp_sections.SHIM_ENV: str(lib), "LD_PRELOAD": str(lib)}
    done = subprocess.run([sys.executable, "-c", CHILD, str(threads)], env=env, capture_output=True, text=True,
                          check=True)
    return done.stdout.strip()


def test_sections_are_counted_on_two_threads_only_while_counting_and_attributed_to_their_operation(tmp_path):
    total, outside, attributed, ops = _child(tmp_path, 2).split(" ", 3)
    assert int(total) >= 1 and outside == "0"
    assert attributed == total and ops == "['aten.exp.default']"
    assert _child(tmp_path, 1) == "0 0 0 []"  # one thread opens no section


def test_the_command_counts_a_training_run(tmp_path):
    done = subprocess.run([sys.executable, "-m", "tools.speed.omp_sections", "--scene", "builtin:garden:tiny",
                           "--methods", "3dgs", "--warmup", "1", "--steps", "2", "--threads", "1"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    # One thread never opens a parallel section.
    assert "3dgs (-, " in done.stdout and ": 0.0 parallel sections a step, 0.0 of them" in done.stdout
