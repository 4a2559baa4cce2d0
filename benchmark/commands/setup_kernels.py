"""``nimbus-bench setup-kernels``: build (or load) the compiled CPU kernels once, so no timed run pays for it.

The libraries of :mod:`nimbus.kernels` (the rasterizer's, :mod:`nimbus.kernels.raster`, the
ray march's, :mod:`nimbus.kernels.march`, and the training step's, :mod:`nimbus.kernels.train_step`)
are built into their cache folders
(:class:`nimbus.kernels.extension.Extension`); later processes only load them.  Optional: a
first render or NimbusGS step builds them just the same, only inside whatever it is timing.
"""

from __future__ import annotations

import argparse
import os
import time

HELP = ("build and cache the compiled CPU kernels (rasterizer, ray march, training loss) now, not inside the first "
        "timed run")
EXAMPLE = "nimbus-bench setup-kernels"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """No options: the cache folder follows ``$NIMBUS_EXT_DIR`` / ``$TORCH_EXTENSIONS_DIR``."""


def run(args: argparse.Namespace) -> int:
    from nimbus.kernels import march, raster, train_step
    from nimbus.kernels.extension import disabled

    if disabled():
        print("NIMBUS_DISABLE_CPP is set: the compiled kernels are disabled, nothing to build "
              "(training uses the torch paths)")
        return 0
    failed = False
    for extension in (raster.EXTENSION, march.EXTENSION, train_step.EXTENSION):
        folder = extension.build_dir()
        cached = folder is not None and os.path.isfile(os.path.join(folder, f"{extension.name}.so"))
        t0 = time.perf_counter()
        ok = extension.available(warn=False)
        seconds = time.perf_counter() - t0
        where = folder or "torch's extension folder"
        if ok:
            print(f"{extension.kernel}: {'loaded (already built)' if cached else 'built'} in {seconds:.1f} s, "
                  f"cached in {where}")
        else:
            failed = True
            print(f"{extension.kernel}: FAILED after {seconds:.1f} s ({extension.load_error()}); "
                  f"{extension.fallback} will be used")
    if failed:
        print("the compiled kernels need a C++ compiler and ninja (pip install ninja); training still works "
              "without them, more slowly")
    return 1 if failed else 0
