"""How many OpenMP parallel sections a training step opens, and which torch operations open them.

Usage::

    python -m tools.speed.omp_sections [--scene SCENE] [--methods restore-3dgs nimbus] [--preset fast]
                                       [--warmup 20] [--steps 20] [--threads 2] [--top 15]

Under ``OMP_WAIT_POLICY=PASSIVE`` every parallel section wakes the sleeping OpenMP threads, so the
number of sections a step opens is part of its cost (docs/performance.md, "A short spin when the
machine is idle").  This tool compiles a small shim around libgomp's ``GOMP_parallel`` (the system C
compiler, ``cc``), runs itself again with the shim preloaded (``LD_PRELOAD``; Linux with GNU libgomp,
which torch's Linux wheels bundle), builds each method as ``nimbus-train`` does (its preset, seed 0),
trains ``--warmup`` untimed steps and then counts the sections of ``--steps`` steps.  A
``TorchDispatchMode`` attributes each section to the torch operation that opened it (forward and
backward alike); the rest are Nimbus's own kernels and the autograd engine's.  Counting changes no
arithmetic.  A weather setting folder (``nimbus-synth degrade``) as ``--scene`` makes NimbusGS build
its medium; on a clean built-in scene ``nimbus`` turns it off.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

from nimbus.errors import NimbusError

#: Environment variable naming the compiled shim in the child run.
SHIM_ENV = "NIMBUS_OMP_SECTIONS_SHIM"

SHIM_SOURCE = r"""
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdatomic.h>
typedef void (*gomp_parallel_fn)(void (*)(void *), void *, unsigned, unsigned);
static atomic_long sections = 0;
static atomic_int counting = 0;
void GOMP_parallel(void (*fn)(void *), void *data, unsigned threads, unsigned flags) {
  static gomp_parallel_fn real = 0;
  if (!real) real = (gomp_parallel_fn)dlsym(RTLD_NEXT, "GOMP_parallel");
  if (atomic_load(&counting)) atomic_fetch_add(&sections, 1);
  real(fn, data, threads, flags);
}
void omp_sections_count(int on) { atomic_store(&counting, on); }
long omp_sections_total(void) { return atomic_load(&sections); }
"""


def build_shim(folder: Path) -> Path:
    """Compile the counting shim into ``folder``; a NimbusError says why it could not be."""
    src, lib = folder / "omp_sections.c", folder / "libomp_sections.so"
    src.write_text(SHIM_SOURCE)
    try:
        done = subprocess.run(["cc", "-O2", "-shared", "-fPIC", str(src), "-o", str(lib), "-ldl"],
                              capture_output=True, text=True)
    except OSError as e:
        raise NimbusError(f"cannot run the C compiler cc ({e}); install one to count sections") from e
    if done.returncode != 0:
        raise NimbusError(f"cannot compile the libgomp shim with cc: {done.stderr.strip()[:300]}")
    return lib


def count_sections(shim: ctypes.CDLL, run) -> tuple[int, Counter]:
    """(sections opened while ``run()`` ran, sections per (torch operation, input shapes))."""
    import torch
    from torch.utils._python_dispatch import TorchDispatchMode

    by_op: Counter = Counter()

    class Attribute(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            before = shim.omp_sections_total()
            out = func(*args, **(kwargs or {}))
            opened = shim.omp_sections_total() - before
            if opened:
                shapes = tuple(tuple(a.shape) for a in args if isinstance(a, torch.Tensor))
                by_op[(str(func), shapes)] += opened
            return out

    start = shim.omp_sections_total()
    shim.omp_sections_count(1)
    try:
        with Attribute():
            run()
    finally:
        shim.omp_sections_count(0)
    return shim.omp_sections_total() - start, by_op


def method_sections(shim: ctypes.CDLL, method_name: str, scene, preset: str, warmup: int, steps: int) -> dict:
    """Sections per step of ``method_name`` on ``scene``: the total, inside torch operations, and by operation."""
    from nimbus.train.runner import Runner
    from tools.speed.training import method_config

    method_name, config = method_config(method_name, preset)
    with tempfile.TemporaryDirectory(prefix="omp_sections_") as out:
        method = Runner(method_name, scene, config, out, seed=0, progress=False, checkpoints=False).method
        last = min(config.iterations, warmup + steps)
        for step in range(1, warmup + 1):
            method.train_iteration(step)

        def run():
            for step in range(warmup + 1, last + 1):
                method.train_iteration(step)

        total, by_op = count_sections(shim, run)
    n = max(1, last - warmup)
    return {"steps": n, "per_step": total / n, "in_torch_ops": sum(by_op.values()) / n,
            "by_op": {k: v / n for k, v in by_op.items()}, "gaussians": len(method.params),
            "components": ",".join(getattr(method, "components", [])) or "-"}


def child_main(args) -> int:
    import torch

    from nimbus.train.run_folder import load_scene_arg

    torch.set_num_threads(args.threads)
    shim = ctypes.CDLL(os.environ[SHIM_ENV])
    scene = load_scene_arg(args.scene)
    results = {}
    for name in args.methods:
        r = method_sections(shim, name, scene, args.preset, args.warmup, args.steps)
        results[name] = r
        print(f"{name} ({r['components']}, {r['gaussians']} Gaussians at the end): {r['per_step']:.1f} parallel "
              f"sections a step, {r['in_torch_ops']:.1f} of them inside torch operations ({r['steps']} steps after "
              f"{args.warmup}, {args.threads} threads)")
        for (op, shapes), k in sorted(r["by_op"].items(), key=lambda kv: -kv[1])[:args.top]:
            print(f"  {k:6.1f}  {op} {list(shapes)}")
    first, *rest = args.methods
    for name in rest:
        if results[first]["per_step"]:
            print(f"{name} / {first}: {results[name]['per_step'] / results[first]['per_step']:.2f}x the sections")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="builtin:garden:tiny", help="builtin:NAME:SIZE or a scene / setting folder")
    parser.add_argument("--methods", nargs="+", default=["restore-3dgs", "nimbus"])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--warmup", type=int, default=20, help="untimed first steps")
    parser.add_argument("--steps", type=int, default=20, help="counted steps")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (1 opens no sections)")
    parser.add_argument("--top", type=int, default=15, help="operations listed per method")
    args = parser.parse_args(argv)
    if os.environ.get(SHIM_ENV):
        return child_main(args)
    if not sys.platform.startswith("linux"):
        raise NimbusError("the section count needs Linux (LD_PRELOAD over GNU libgomp)")
    with tempfile.TemporaryDirectory(prefix="omp_sections_shim_") as folder:
        lib = build_shim(Path(folder))
        env = {**os.environ, SHIM_ENV: str(lib),
               "LD_PRELOAD": " ".join(p for p in (str(lib), os.environ.get("LD_PRELOAD", "")) if p)}
        argv = sys.argv[1:] if argv is None else list(argv)
        return subprocess.run([sys.executable, "-m", "tools.speed.omp_sections", *argv], env=env).returncode


if __name__ == "__main__":
    from nimbus.cli_util import run_cli

    raise SystemExit(run_cli(main))
